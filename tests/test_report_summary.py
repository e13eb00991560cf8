"""report summary: the results come first, beside the paper's values, and no cell is left blank."""

from __future__ import annotations

import json
import re

import numpy as np
import pandas as pd
from test_report_build import _results

from waveforest.report.summary import fig9_sentences, table3_summary, table4_summary
from waveforest.stages.report import run


def _sections(md: str) -> list[tuple[str, str]]:
    """(title, body) of every ``## `` section of a Markdown report."""
    parts = re.split(r"^## (.+)$", md, flags=re.M)
    return list(zip(parts[1::2], parts[2::2]))


def _cells(body: str) -> list[str]:
    """Every cell of every pipe-table row in ``body`` (header rows included)."""
    out = []
    for line in body.splitlines():
        if line.startswith("|") and not set(line) <= set("|-"):
            out += [c.strip() for c in re.split(r"(?<!\\)\|", line)[1:-1]]
    return out


def _old_style_json(dataset: str) -> dict:
    """A classify JSON of the first format: null levels, no ``reason``, zero groups in pulses_per_group."""
    return {"dataset": dataset, "n_pulses": 12, "n_samples": 3, "pulses_per_sample": 4.0,
            "pulses_per_group": {"conifer": 0, "broadleaf": 0, "low_green": 12, "low_barren_abiotic": 0},
            "main": {"features": ["E", "Apeak"], "one_pulse": None, "mean_of_sample": None}}


def test_summary_first_with_both_tables_and_paper_values(tmp_path):
    res, cfg = _results(tmp_path)
    cfg = dict(cfg, datasets=["2010_12_1", "2012_10_1", "2012_05_1"])
    (res / "classify" / "2012_05_1.json").write_text(json.dumps(_old_style_json("2012_05_1")))
    out = run(res, res / "report" / "report.html", cfg)
    md = out.markdown.read_text()
    sections = _sections(md)
    assert sections[0][0] == "What this report ran on"
    title, body = sections[1]
    assert title.startswith("Summary")
    # the summary precedes every detail section, calibration included
    titles = [t for t, _ in sections]
    assert titles.index("System waveform calibration and AGC (docs/method.md §(b), e)") > titles.index(
        "Real-data classification (Table 4; docs/method.md §(i4))") > 1
    assert "Table 3 in brief" in body and "Table 4 in brief" in body
    rows = {line.split("|")[1].strip() + "/" + line.split("|")[2].strip(): line for line in body.splitlines()
            if line.startswith("| 20")}
    # Table 3: ours (-12.857 %, 50 real / 40 simulated pulses) beside the paper's (Apeak -19 %, N 1733)
    birch = [c.strip() for c in rows["2010_12_1/birch"].split("|")[1:-1]]
    assert birch[:4] == ["2010_12_1", "birch", "50 / 40", "1733"]
    assert "-12.9" in birch and "-19" in birch
    # ...the features not in our table are explained, and so are datasets of the paper we did not compare
    assert "— (H not compared)" in birch
    assert "— (dataset not in comparison)" in rows["2012_05_1/birch"]
    # ...and the paper's datasets not in this run are left out, with one line saying so
    assert "2012_27_1/birch" not in rows and "dataset not in this run" not in md
    assert "Left out of Table 3 in brief: the paper's datasets 2012_20_1, 2012_27_1, not in this run." in body
    # Table 4: the paper's 2012_10_1 (83.1 %, kappa 0.76) beside ours; an old-style JSON with null
    # levels explained from its pulses_per_group
    t4 = [c.strip() for c in [ln for ln in body.splitlines() if ln.startswith("| 2012_10_1 | ")
                              and "(κ" in ln][0].split("|")[1:-1]]
    assert "83.1 (κ 0.76)" in t4 and "100.0 (κ 1.00)" in t4
    old = [ln for ln in body.splitlines() if ln.startswith("| 2012_05_1 | 12 (3)")][0]
    assert "— (0 pulses of conifer, broadleaf, low_barren_abiotic; LDA needs 2 groups with pulses)" in old
    assert "76.1 (κ 0.66)" in old
    assert ("our 1-pulse accuracy is 100.0 % by resubstitution and 100.0 % cross-validated; the paper's for the "
            "same datasets 76.1 to 83.1 % (all 9: 68.1 to 86.7 %)") in body
    assert "— (detection limits not computed" in body
    # no empty cell anywhere in the report, summary or details
    for _, b in sections:
        cells = _cells(b)
        assert cells and all(cells), "empty cell"
    assert "||" not in md and "| |" not in md


def test_missing_values_explained_from_new_style_json_and_detection_limits(tmp_path):
    res, cfg = _results(tmp_path)
    r = json.loads((res / "classify" / "2012_10_1.json").read_text())
    r["main"].update(one_pulse=None, mean_of_sample=None, reason="LDA needs at least 2 functional groups "
                     "with pulses; only low_green has any (0 pulses: conifer)")
    (res / "classify" / "2012_10_1.json").write_text(json.dumps(r))
    pd.DataFrame(dict(effect=["understory", "clumping"], unit=["", "m"], smallest_detectable=[0.4, np.nan],
                      upper_bound=[2.0, 3.0], power=[0.8, 0.8], replicates=[4, 4])).to_csv(
        res / "diagnose" / "detection_limits.csv", index=False)
    md = run(res, res / "report" / "report.html", cfg).markdown.read_text()
    title, body = _sections(md)[1]
    assert "— (LDA needs at least 2 functional groups with pulses; only low_green has any (0 pulses: conifer))" in body
    assert "Detection limits of the diagnosis" in body
    lim = {ln.split("|")[1].strip(): [c.strip() for c in ln.split("|")[1:-1]]
           for ln in body.splitlines() if ln.startswith(("| understory", "| clumping"))}
    assert lim["understory"][1] == "0.4" and lim["clumping"][1] == "— (nothing up to 3 m is detectable)"
    assert ("Detection limits (power 0.80): understory from 0.4 would have been detected; 1 of 2 effects are not "
            "detectable within their bounds. The range tried") in body
    assert "one pseudo-real replicate" not in body  # 4 replicates
    assert "verdict" in body  # model.yaml of the fixture has none: said so in place
    assert "— (model.yaml holds no verdict)" in body
    cells = _cells(body)
    assert cells and all(cells)


def test_table3_summary_explains_zero_counts():
    ours = pd.DataFrame(dict(dataset="2012_10_1", species=["fireweed"] * 2, feature=["H", "Apeak"],
                             delta_pct=[np.nan, np.nan], n_real=[5, 5], n_sim=[0, 0],
                             sim_mean=np.nan, real_mean=[0.5, 100.0]))
    t = table3_summary(ours, ["2012_10_1"])
    row = t[(t.dataset == "2012_10_1") & (t.species == "fireweed")].iloc[0]
    assert row["N real / sim"] == "5 / 0" and row["N paper"] == "1758"
    assert row["Apeak Δ%"] == "— (0 simulated pulses)" and row["Apeak Δ% paper"] == "+5"
    assert len(t) == 15 and not t.isna().any().any()  # every (dataset, species) of the paper's Table 3
    assert table3_summary(None).iloc[0]["E Δ%"] == "— (compare not run)"


def test_table4_summary_rows_ours_first_then_the_papers():
    t = table4_summary([_old_style_json("my_site")], ["my_site"])
    assert t["dataset"].tolist()[0] == "my_site" and len(t) == 10
    mine = t.iloc[0]
    assert mine["1-pulse paper"] == "— (not in the paper)"
    assert mine["pulses/sample"] == "4.0" and mine["pulses/sample paper"] == "— (not in the paper)"
    paper_only = t[t.dataset == "2012_27_1"].iloc[0]
    assert paper_only["1-pulse paper"] == "86.7 (κ 0.80)" and paper_only["1-pulse resub"] == "— (dataset not in this run)"


def test_fig9_trend_finds_the_maximum_and_places_it_against_the_paper():
    # accuracy rises to its maximum at 0.30 mrad (0.36 m at 1200 m), then stays there
    div = [0.05, 0.1, 0.2, 0.3, 0.5, 0.7]
    acc = [0.60, 0.70, 0.80, 0.95, 0.95, 0.95]
    ss = pd.DataFrame([dict(parameter="divergence_mrad", value=v, level="1-pulse", scheme="resubstitution",
                            accuracy=a, n=1500) for v, a in zip(div, acc)]
                      + [dict(parameter="sampling_ns", value=v, level="1-pulse", scheme="resubstitution",
                              accuracy=0.8, n=1500) for v in (0.25, 4.0)])
    s = fig9_sentences(ss, 1200.0)
    assert "1-pulse accuracy rises with footprint from 60.0 % at 0.06 m to 95.0 % at 0.84 m" in s
    assert "first reached at 0.36 m, within the paper's 0.30-0.36 m" in s
    assert "within 80.0-80.0 % over sampling intervals 0.25-4 ns" in s
    assert "pulse widths: — (not in sensor_study.csv)" in s
    # at 600 m the same curve peaks at 0.18 m: below the paper's range
    assert "first reached at 0.18 m, below the paper's" in fig9_sentences(ss, 600.0)
