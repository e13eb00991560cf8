"""compare: Table 3 statistics and Delta % on known inputs, the birch H rule, order checks."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from fixtures.tables import pulse_table

from waveforest import config
from waveforest.analysis.compare import order_check, table3, with_paper
from waveforest.cli import main
from waveforest.io.pulses import write_pulses
from waveforest.sensor.waveforms import align_on_echo
from waveforest.stages.compare import run


def _feat(dataset, species, source, h, apeak, e, fwhm, npeaks, start=0):
    n = len(h)
    return pd.DataFrame(dict(dataset=dataset, pulse_id=np.arange(start, start + n), source=source,
                             species=species, sample_id=f"{species}-1", H=h, Apeak=apeak, E=e,
                             FWHM=fwhm, Npeaks=npeaks, n_echoes=1))


def test_delta_pct_and_sd_on_known_values():
    real = _feat("d", "raspberry", "real", [0.5, 0.7], [100.0, 120.0], [1000.0, 1400.0], [9.0, 11.0], [1, 1])
    sim = _feat("d", "raspberry", "sim", [0.6, 0.6, 0.9], [99.0, 121.0, 110.0], [1320.0] * 3,
                [10.0, 10.0, 13.0], [1, 1, 2])
    t = table3(real, sim, {}).set_index("feature")
    assert t.loc["Apeak", "real_mean"] == 110.0 and t.loc["Apeak", "sim_mean"] == pytest.approx(110.0)
    assert t.loc["Apeak", "delta_pct"] == pytest.approx(0.0, abs=1e-12)
    assert t.loc["E", "delta_pct"] == pytest.approx(10.0)
    assert t.loc["E", "real_sd"] == pytest.approx(np.std([1000, 1400], ddof=1))
    assert t.loc["E", "sim_sd"] == pytest.approx(0.0)
    assert t.loc["H", "delta"] == pytest.approx(0.1)
    assert t.loc["H", "delta_pct"] == pytest.approx(100 * 0.1 / 0.6)
    assert t.loc["FWHM", "delta_pct"] == pytest.approx(100 * (11.0 - 10.0) / 10.0)
    assert t.loc["Npeaks", "sim_mean"] == pytest.approx(4 / 3)
    assert (t["n_real"] == 2).all() and (t["n_sim"] == 3).all()
    assert list(t.index) == ["H", "Npeaks", "Apeak", "FWHM", "E"]


def test_birch_waveform_features_use_high_echoes_only():
    real = _feat("d", "birch", "real", [0.5, 2.0, 3.0], [200.0, 60.0, 80.0], [1.0] * 3, [10.0] * 3, [1] * 3)
    sim = _feat("d", "birch", "sim", [1.4, 2.5], [300.0, 70.0], [1.0] * 2, [10.0] * 2, [1] * 2)
    t = table3(real, sim, {"birch": 1.5}).set_index("feature")
    assert t.loc["Apeak", "real_mean"] == 70.0 and t.loc["Apeak", "n_real"] == 2
    assert t.loc["Apeak", "sim_mean"] == 70.0 and t.loc["Apeak", "n_sim"] == 1
    assert t.loc["H", "n_real"] == 3 and t.loc["H", "real_mean"] == pytest.approx(5.5 / 3)


def test_order_check_against_paper():
    rows = []
    for sp, a in (("birch", 60.0), ("raspberry", 110.0), ("fireweed", 90.0)):
        rows.append(_feat("2010_12_1", sp, "sim", [1.0] * 2, [a, a], [a * 10] * 2, [10.0] * 2, [1] * 2))
    sim = pd.concat(rows, ignore_index=True)
    real = sim.assign(source="real")
    t = with_paper(table3(real, sim, {}))
    assert t.loc[(t.species == "birch") & (t.feature == "Apeak"), "paper_sim_mean"].item() == 59.3
    c = order_check(t).set_index("feature")
    assert c.loc["Apeak", "order_sim"] == "raspberry > fireweed > birch"
    assert c.loc["Apeak", "order_paper_sim"] == "raspberry > fireweed > birch"
    assert c.loc["Apeak", "sim_matches_paper"] and c.loc["E", "sim_matches_paper"]
    assert c.loc["Apeak", "max_abs_dev_from_paper_sim_pct"] == pytest.approx(100 * (90 - 87.8) / 87.8, rel=1e-6)  # fireweed is farthest


def test_align_on_echo_is_exact_for_linear_waveforms():
    t = np.arange(50.0)
    samples = np.vstack([2 * t + 1, 3 * t])
    out = align_on_echo(samples, np.array([50, 40]), np.array([1.0, 2.0]), np.array([10.0, 20.5]),
                        np.array([-5.0, 0.0, 0.25, 100.0]))
    # row 0: times 5, 10, 10.25 ns at 1 ns -> 2t+1; row 1: sample index = time / 2
    assert out[0, :3] == pytest.approx([11.0, 21.0, 21.5])
    assert out[1, :3] == pytest.approx([3 * 7.75, 3 * 10.25, 3 * 10.375])
    assert np.isnan(out[:, 3]).all()


def test_run_writes_tables_and_figures(tmp_path):
    rng = np.random.default_rng(0)
    echoes_r = [[(0.0, 0.0, 100.0 + 0.6 + 0.1 * rng.standard_normal())] for _ in range(12)]
    echoes_s = [[(0.0, 0.0, 100.0 + 0.5 + 0.1 * rng.standard_normal())] for _ in range(12)]
    pr = pulse_table("2010_12_1", echoes_r).to_pandas()
    pr["species"], pr["sample_id"], pr["comparison_set"], pr["height_m"] = "raspberry", "R1", True, 1.0
    ps = pulse_table("2010_12_1", echoes_s, source="sim").to_pandas()
    import pyarrow as pa

    write_pulses(pa.Table.from_pandas(pr, preserve_index=False), tmp_path / "sel.parquet")
    write_pulses(pa.Table.from_pandas(ps, preserve_index=False), tmp_path / "sim0.parquet")
    fr = _feat("2010_12_1", "raspberry", "real", rng.normal(0.6, 0.1, 12), rng.normal(108, 9, 12),
               rng.normal(1300, 100, 12), rng.normal(9, 1, 12), np.ones(12))
    fs = _feat("2010_12_1", "raspberry", "sim", rng.normal(0.5, 0.1, 12), rng.normal(110, 9, 12),
               rng.normal(1320, 100, 12), rng.normal(10, 1, 12), np.ones(12))
    fr.drop(columns=["sample_id"]).to_parquet(tmp_path / "fr.parquet")
    fs.to_parquet(tmp_path / "fs.parquet")
    cfgp = tmp_path / "c.yaml"
    cfgp.write_text("seed: 1\n")
    main(["compare", "--real", str(tmp_path / "fr.parquet"), "--sim", str(tmp_path / "fs.parquet"),
          "--pulses-real", str(tmp_path / "sel.parquet"), "--pulses-sim", str(tmp_path / "sim0.parquet"),
          "--out", str(tmp_path / "out"), "--config", str(cfgp)])
    t = pd.read_csv(tmp_path / "out" / "table3.csv")
    assert len(t) == 5 and not t[["sim_mean", "real_mean", "delta_pct"]].isna().any().any()
    assert t.loc[t.feature == "Apeak", "paper_sim_mean"].item() == 110.9
    md = (tmp_path / "out" / "table3.md").read_text()
    assert "| 2010_12_1 | raspberry | Apeak |" in md
    for name in ("fig6_2010_12_1.png", "fig7_2010_12_1.png", "order_check.csv"):
        assert (tmp_path / "out" / name).stat().st_size > 1000 or name.endswith(".csv")
    cfg = config.load(cfgp)
    r = run([tmp_path / "fr.parquet"], [tmp_path / "fs.parquet"], [], [], tmp_path / "o2", cfg)
    assert r.table_csv.exists()


def test_multi_value_options():
    import click
    from click.testing import CliRunner

    from waveforest.cliutil import MultiValueCommand, MultiValueOption

    @click.command(cls=MultiValueCommand)
    @click.argument("first")
    @click.option("--a", cls=MultiValueOption)
    @click.option("--b", cls=MultiValueOption)
    @click.option("--out")
    def cmd(first, a, b, out):
        click.echo(f"{first}|{','.join(a)}|{','.join(b)}|{out}")

    r = CliRunner().invoke(cmd, ["p", "--a", "1", "2", "3", "--out", "o", "--b", "x", "--a", "4"])
    assert r.exit_code == 0, r.output
    assert r.output.strip() == "p|1,2,3,4|x|o"
    r = CliRunner().invoke(cmd, ["p", "--out", "o"])
    assert r.output.strip() == "p|||o"
