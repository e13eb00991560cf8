"""select: exact membership on synthetic pulses of known geometry (docs/method.md §(i1), i4)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from fixtures.tables import pulse_table

from waveforest import config
from waveforest.cli import main
from waveforest.io.pulses import read_pulses
from waveforest.io.tables import CampaignTableError, read_datasets, read_fields
from waveforest.model.selection import SelectRules, match_samples, select_pulses
from waveforest.stages.select import run

FIELDS = pd.DataFrame(
    [
        # tree: radius_m is large on purpose, select must use tree_radius_m = 0.5
        dict(sample_id="T1", year=2010, species="birch", functional_group="broadleaf", x=0.0, y=0.0,
             ground_z=100.0, height_m=3.0, radius_m=2.0, is_tree=True),
        dict(sample_id="T2", year=2010, species="birch", functional_group="broadleaf", x=0.0, y=10.0,
             ground_z=100.0, height_m=6.0, radius_m=0.5, is_tree=True),
        dict(sample_id="L1", year=2010, species="raspberry", functional_group="low_green", x=10.0, y=0.0,
             ground_z=101.0, height_m=1.2, radius_m=1.0, is_tree=False),
        dict(sample_id="L2", year=2010, species="raspberry", functional_group="low_green", x=10.0, y=1.5,
             ground_z=101.0, height_m=1.0, radius_m=1.0, is_tree=False),
        dict(sample_id="X1", year=2012, species="fireweed", functional_group="low_green", x=20.0, y=0.0,
             ground_z=0.0, height_m=1.0, radius_m=1.0, is_tree=False),
    ]
)

ECHOES = [
    [(0.3, 0.3, 102.0)],                        # 0: T1 (0.42 m, H 2)
    [(0.4, 0.4, 102.0)],                        # 1: 0.57 m from T1: outside the tree radius
    [(0.1, 0.0, 100.5)],                        # 2: T1 but H 0.5 < 1 m: below its crown
    [(10.5, 0.0, 101.2)],                       # 3: L1 (0.5 m)
    [(10.0, 0.8, 101.3)],                       # 4: L1 0.8 m, L2 0.7 m -> L2
    [(20.0, 0.0, 0.5)],                         # 5: sample of another year
    [],                                         # 6: no echo
    [(10.0, -0.5, 101.5), (10.0, -0.5, 101.0)],  # 7: L1, two echoes
    [(10.9, 0.0, 101.0)],                       # 8: L1 (0.9 m)
    [(0.0, 10.2, 105.0)],                       # 9: T2, birch of 6 m: outside the comparison heights
    [(0.0, 10.1, 100.3)],                       # 10: below T2's crown, but T2 is not compared: dropped
]

EXPECTED = {0: "T1", 2: "T1", 3: "L1", 4: "L2", 7: "L1", 8: "L1", 9: "T2"}


def _rules(min_pulses=2):
    return SelectRules(tree_radius_m=0.5, tree_min_echo_h_m=1.0, min_pulses=min_pulses)


def test_membership_is_exact():
    out = select_pulses(pulse_table("2010_12_1", ECHOES), FIELDS, 2010, _rules())
    got = dict(zip(out.column("pulse_id").to_pylist(), out.column("sample_id").to_pylist()))
    assert got == EXPECTED
    h = dict(zip(out.column("pulse_id").to_pylist(), out.column("first_echo_h_m").to_pylist()))
    assert h[0] == pytest.approx(2.0) and h[4] == pytest.approx(0.3)
    d = dict(zip(out.column("pulse_id").to_pylist(), out.column("sample_distance_m").to_pylist()))
    assert d[0] == pytest.approx(np.hypot(0.3, 0.3)) and d[4] == pytest.approx(0.7)


def test_flags():
    out = select_pulses(pulse_table("2010_12_1", ECHOES), FIELDS, 2010, _rules(min_pulses=2)).to_pandas()
    out = out.set_index("pulse_id")
    # single-echo raspberry pulses: 3, 4, 8 (>= 2); birch single-echo: 0, 9 -> 2 (>= 2)
    assert out.loc[[0, 3, 4, 8, 9], "classification_set"].all()
    assert not out.loc[7, "classification_set"]  # two DR echoes
    # comparison: birch only 2.5-5 m -> T2 (6 m) out; raspberry in
    assert out.loc[[0, 3, 4, 7, 8], "comparison_set"].all()
    assert not out.loc[9, "comparison_set"]
    out3 = select_pulses(pulse_table("2010_12_1", ECHOES), FIELDS, 2010, _rules(min_pulses=3)).to_pandas()
    out3 = out3.set_index("pulse_id")
    assert not out3.loc[[0, 9], "classification_set"].any()  # birch: 2 < 3 pulses
    assert out3.loc[[3, 4, 8], "classification_set"].all()


def test_below_crown_pulses_are_a_set_of_their_own():
    """A first echo under a compared tree's crown joins that tree in below_crown_set only;
    any sample that takes it by the ordinary rules wins."""
    out = select_pulses(pulse_table("2010_12_1", ECHOES), FIELDS, 2010, _rules(min_pulses=1)).to_pandas()
    out = out.set_index("pulse_id")
    assert out.index[out["below_crown_set"]].tolist() == [2]
    assert not out.loc[2, ["classification_set", "comparison_set"]].any()  # single echo, birch 3 m
    assert out.loc[2, "first_echo_h_m"] == pytest.approx(0.5)
    assert 10 not in out.index  # under a birch of 6 m
    # a low echo inside a tree's radius and a low sample's radius belongs to the low sample
    f = pd.concat([FIELDS, FIELDS.iloc[[2]].assign(sample_id="L3", x=0.6, y=0.0, ground_z=100.0)])
    both = select_pulses(pulse_table("2010_12_1", [[(0.1, 0.0, 100.5)]]), f, 2010, _rules()).to_pandas()
    assert both["sample_id"].tolist() == ["L3"] and not both["below_crown_set"].any()


def test_far_candidates_are_not_missed():
    """Nine nearer tree samples fail the height rule; the farther low sample must still win."""
    rows = [dict(x=0.01 * (i + 1), y=0.0, ground_z=0.0, radius_m=0.5, is_tree=True) for i in range(9)]
    rows.append(dict(x=0.6, y=0.0, ground_z=0.0, radius_m=1.0, is_tree=False))
    f = pd.DataFrame(rows)
    idx, dist = match_samples(np.array([[0.0, 0.0, 0.5], [0.0, 0.0, 1.5], [5.0, 5.0, 0.0]]), f, _rules())
    assert idx.tolist() == [9, 0, -1]
    assert dist[0] == pytest.approx(0.6) and dist[1] == pytest.approx(0.01) and np.isnan(dist[2])


def _config_file(tmp_path, text):
    path = tmp_path / "config.yaml"
    path.write_text(text)
    return path


def test_run_and_cli(tmp_path):
    pulses = tmp_path / "p.parquet"
    from waveforest.io.pulses import write_pulses

    write_pulses(pulse_table("2010_12_1", ECHOES), pulses)
    FIELDS.assign(is_tree=FIELDS["is_tree"].astype(int)).to_csv(tmp_path / "fields.csv", index=False)
    pd.DataFrame([dict(dataset="2010_12_1", year=2010, mean_range_m=1200, pulse_width_fwhm_ns=7.2,
                       footprint_diameter_m=0.18, sampling_ns=1)]).to_csv(tmp_path / "datasets.csv", index=False)
    cfg = config.load(overrides={"select": {"min_pulses": 2}})
    s = run(pulses, tmp_path / "fields.csv", tmp_path / "datasets.csv", tmp_path / "sel.parquet", cfg)
    assert (s.n_pulses, s.n_selected, s.n_samples, s.n_below_crown) == (11, 7, 4, 1)
    out = read_pulses(tmp_path / "sel.parquet")
    assert sorted(out.column("pulse_id").to_pylist()) == sorted(EXPECTED)
    main(["select", str(pulses), "--fields", str(tmp_path / "fields.csv"), "--datasets",
          str(tmp_path / "datasets.csv"), "--out", str(tmp_path / "cli.parquet"), "--config",
          str(_config_file(tmp_path, "select:\n  min_pulses: 2\n"))])
    assert read_pulses(tmp_path / "cli.parquet").num_rows == 7


def test_bad_tables(tmp_path, capsys):
    (tmp_path / "fields.csv").write_text("sample_id,year,x\nA,2010,1\n")
    with pytest.raises(CampaignTableError, match="missing column"):
        read_fields(tmp_path / "fields.csv")
    (tmp_path / "datasets.csv").write_text(
        "dataset,year,mean_range_m,pulse_width_fwhm_ns,footprint_diameter_m,sampling_ns\n"
        "a,2010,twelve,7,0.1,1\n")
    with pytest.raises(CampaignTableError, match="mean_range_m, row 2"):
        read_datasets(tmp_path / "datasets.csv")
    pulses = tmp_path / "p.parquet"
    from waveforest.io.pulses import write_pulses

    write_pulses(pulse_table("2010_12_1", ECHOES), pulses)
    with pytest.raises(SystemExit) as e:
        main(["select", str(pulses), "--fields", str(tmp_path / "fields.csv"), "--datasets",
              str(tmp_path / "datasets.csv"), "--out", str(tmp_path / "o.parquet")])
    assert e.value.code == 1
    assert "datasets.csv: column mean_range_m" in capsys.readouterr().err
    assert not list(tmp_path.glob("o.parquet*")) and not list(tmp_path.glob(".o.parquet*"))
