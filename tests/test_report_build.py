"""report: the HTML and Markdown contain every table and figure of a results folder."""

from __future__ import annotations

import json
import re

import numpy as np
import pandas as pd
import pytest
from test_analysis_classify import _features

from waveforest import config
from waveforest.analysis.classify import classify_dataset
from waveforest.cli import main
from waveforest.errors import WaveforestError
from waveforest.report import plots
from waveforest.settings import classify_settings
from waveforest.stages.report import run


def _results(tmp_path):
    res = tmp_path / "results"
    (res / "compare").mkdir(parents=True)
    pd.DataFrame(dict(dataset=["2010_12_1"], species=["birch"], feature=["Apeak"], sim_mean=[61.0], sim_sd=[12.0],
                      real_mean=[70.0], real_sd=[13.0], delta_pct=[-12.857], n_sim=[40], n_real=[50],
                      paper_sim_mean=[59.3])).to_csv(res / "compare" / "table3.csv", index=False)
    plots.fig6_heights({"birch": np.array([2.0, 2.5])}, {"birch": np.array([2.2, 2.7])}, "2010_12_1",
                       res / "compare" / "fig6_2010_12_1.png")
    (res / "sensitivity").mkdir()
    sens = pd.DataFrame(dict(parameter=["baseline", "leaf_rho", "leaf_rho"], value=[np.nan, 0.4, 0.5],
                             mean_apeak=[55.0, 52.0, 66.0], se_apeak=[1.0, 1.1, 1.2]))
    sens.to_csv(res / "sensitivity" / "sensitivity.csv", index=False)
    plots.fig8_sensitivity(sens, res / "sensitivity" / "fig8.png")
    (res / "sensor_study").mkdir()
    ss = pd.DataFrame([dict(parameter="sampling_ns", value=v, level=lv, scheme=sc, accuracy=0.8, kappa=0.7, n=30)
                       for v in (1.0, 2.0) for lv in ("1-pulse", "5-pulse") for sc in ("resubstitution", "cross_validated")])
    ss.to_csv(res / "sensor_study" / "sensor_study.csv", index=False)
    plots.fig9_sensor(ss, res / "sensor_study" / "fig9.png")
    (res / "classify").mkdir()
    cfg = config.load(overrides={"select": {"min_pulses": 5}})
    r = classify_dataset(_features(np.random.default_rng(0)), classify_settings(cfg))
    r["dataset"] = "2012_10_1"
    (res / "classify" / "2012_10_1.json").write_text(json.dumps(r))
    (res / "calibration").mkdir()
    (res / "calibration" / "2012_10_1.json").write_text(json.dumps(dict(noise_mean=10.2, noise_sd=1.4, fwhm_ns=10.1)))
    (res / "diagnose").mkdir()
    (res / "diagnose" / "model.yaml").write_text("effects: {understory: 1.2}\n")
    pd.DataFrame(dict(effect=["understory"], gap=[0.3])).to_csv(res / "diagnose" / "candidates.csv", index=False)
    (res / "extra").mkdir()
    pd.DataFrame(dict(a=[1], b=[2])).to_csv(res / "extra" / "something.csv", index=False)
    (res / "benchmarks" / "simulate").mkdir(parents=True)
    (res / "benchmarks" / "simulate" / "2010_12_1_0.tsv").write_text(
        "s\th:m:s\tmax_rss\tmax_vms\tmax_uss\tmax_pss\tio_in\tio_out\tmean_load\tcpu_time\n"
        "12.5\t0:00:12\t300.1\t900\t250\t260\t0\t1\t95\t11.9\n")
    (res / "campaign").mkdir()
    pd.DataFrame(dict(x=[1])).to_csv(res / "campaign" / "fields.csv", index=False)  # not a result table
    return res, cfg


def test_report_has_every_table_and_figure(tmp_path):
    res, cfg = _results(tmp_path)
    out = run(res, res / "report" / "report.html", cfg)
    page = out.html.read_text()
    md = out.markdown.read_text()
    n_png = len(list(res.rglob("*.png")))
    assert page.count("data:image/png;base64,") == n_png == out.n_figures == 3
    for caption in ("Table 3 analogue", "Sensitivity", "Overall accuracy", "Table 4 analogue", "Confusion matrix",
                    "candidates.csv", "extra/something.csv", "Wall time per stage", "Software versions",
                    "Calibration per dataset"):
        assert caption in page and caption in md
    assert "<caption>campaign/fields.csv" not in page  # the campaign folder is input, not a result
    assert "understory: 1.2" in page and "seed: " in page
    assert re.search(r"<td>numpy</td><td>\d", page)
    t4 = pd.read_csv(res / "report" / "table4.csv")
    assert t4.loc[0, "paper_one_pulse_correct_pct"] == 83.1 and t4.loc[0, "one_pulse_correct_pct"] == 100.0
    # Markdown links point at files that exist
    for link in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", md):
        assert (out.markdown.parent / link).exists()
    assert "| 2010_12_1 | birch | Apeak | 61.0 | 12.0 | 70.0 | 13.0 | -12.86 |" in md


def test_report_cli(tmp_path):
    res, _ = _results(tmp_path)
    cfgp = tmp_path / "c.yaml"
    cfgp.write_text("seed: 3\n")
    main(["report", "--results", str(res), "--config", str(cfgp), "--out", str(tmp_path / "r" / "report.html")])
    assert (tmp_path / "r" / "report.html").stat().st_size > 10000
    assert "seed: 3" in (tmp_path / "r" / "report.md").read_text()


def test_report_of_a_folder_without_results_is_an_error_and_writes_nothing(tmp_path):
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "notes.txt").write_text("mine")
    out = tmp_path / "r" / "report.html"
    with pytest.raises(WaveforestError, match=r"empty: no result of a run found"):
        run(tmp_path / "empty", out, None)
    assert not (tmp_path / "r").exists()
