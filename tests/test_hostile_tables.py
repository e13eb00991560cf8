"""Hostile campaign tables and options through the CLI stage that reads them: each ends in
one message naming the file (and row or field) and what was expected, exit code != 0, and no
output left behind."""

from __future__ import annotations

import pandas as pd
import pytest
from fixtures.tables import pulse_table

from waveforest.cli import main
from waveforest.io.pulses import write_pulses

DATASET = dict(dataset="2010_12_1", year=2010, mean_range_m=1200, pulse_width_fwhm_ns=7.2,
               footprint_diameter_m=0.18, sampling_ns=1.0)
FIELD = dict(sample_id="T1", year=2010, species="birch", functional_group="broadleaf", x=0.0, y=0.0,
             ground_z=100.0, height_m=3.0, radius_m=0.5, is_tree=1)
TARGET = dict(target_id="tarp", year=2010, material="tarp", hdrf=0.34, calibration=1, agc=1, x=0.0, y=0.0,
              z=100.0, radius_m=2.0)


@pytest.fixture()
def campaign(tmp_path):
    """A one-dataset campaign: a pulse table and valid datasets, fields and targets tables."""
    pulses = tmp_path / "pulses.parquet"
    write_pulses(pulse_table("2010_12_1", [[(0.1, 0.1, 102.0)], [(5.0, 5.0, 100.0)]]), pulses)
    _write(tmp_path / "datasets.csv", [DATASET])
    _write(tmp_path / "fields.csv", [FIELD])
    _write(tmp_path / "targets.csv", [TARGET])
    return tmp_path, pulses


def _write(path, rows):
    pd.DataFrame(rows).to_csv(path, index=False)
    return path


def _fails(argv, capsys, out_dir, *expected):
    """Run the CLI: exit 1, one `waveforest: error:` line with every ``expected`` text, no output."""
    before = set(out_dir.iterdir())
    with pytest.raises(SystemExit) as exc:
        main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert exc.value.code != 0, err
    assert "Traceback" not in err
    for text in expected:
        assert text in err, err
    assert set(out_dir.iterdir()) == before  # nothing written, not even a .part
    return err


def _select(tmp, pulses, fields="fields.csv", datasets="datasets.csv", *extra):
    return ["select", pulses, "--fields", tmp / fields, "--datasets", tmp / datasets, "--out", tmp / "o.parquet",
            *extra]


def _agc(tmp, pulses, targets="targets.csv", datasets="datasets.csv"):
    return ["agc", pulses, "--targets", tmp / targets, "--datasets", tmp / datasets, "--out", tmp / "o.parquet",
            "--fit", tmp / "o.json"]


@pytest.mark.parametrize("column, value, expected", [
    ("species", "oak", ["unknown species 'oak'", "birch", "sand_road"]),
    ("species", "Birch", ["unknown species 'Birch'", "birch"]),
    ("functional_group", "trees", ["unknown functional group 'trees'",
                                   "conifer, broadleaf, low_green, low_barren_abiotic"]),
    ("x", "inf", ["column x, row 3: inf; expected a finite number (m)"]),
    ("ground_z", "nan", ["column ground_z, row 3: empty value"]),
    ("height_m", "-1", ["column height_m, row 3: -1; expected [0, 150] m"]),
])
def test_bad_fields_row(campaign, capsys, column, value, expected):
    tmp, pulses = campaign
    _write(tmp / "bad_fields.csv", [FIELD, {**FIELD, "sample_id": "T2", column: value}])
    err = _fails(_select(tmp, pulses, fields="bad_fields.csv"), capsys, tmp, "bad_fields.csv", *expected)
    assert "row 3" in err  # the second data row


@pytest.mark.parametrize("column, value, expected", [
    ("mean_range_m", "inf", "column mean_range_m, row 2: inf; expected (0, 100000) m"),
    ("mean_range_m", "-5", "column mean_range_m, row 2: -5"),
    ("divergence_mrad", "-0.2", "column divergence_mrad, row 2: -0.2; expected (0, 100] mrad"),
    ("sampling_ns", "0", "column sampling_ns, row 2: 0"),
    ("year", "inf", "column year, row 2"),
])
def test_bad_datasets_value(campaign, capsys, column, value, expected):
    tmp, pulses = campaign
    _write(tmp / "bad_datasets.csv", [{**DATASET, column: value}])
    _fails(_select(tmp, pulses, datasets="bad_datasets.csv"), capsys, tmp, "bad_datasets.csv", expected)
    _fails(_agc(tmp, pulses, datasets="bad_datasets.csv"), capsys, tmp, "bad_datasets.csv", expected)


@pytest.mark.parametrize("column, value, expected", [
    ("hdrf", "40", "column hdrf, row 2: 40; expected (0, 1]"),
    ("hdrf", "0", "column hdrf, row 2: 0; expected (0, 1]"),
    ("hdrf", "", "calibration target 'tarp' needs an HDRF"),
    ("z", "-inf", "column z, row 2: -inf"),
    ("radius_m", "0", "column radius_m, row 2: 0"),
])
def test_bad_targets_value(campaign, capsys, column, value, expected):
    tmp, pulses = campaign
    _write(tmp / "bad_targets.csv", [{**TARGET, column: value}])
    _fails(_agc(tmp, pulses, targets="bad_targets.csv"), capsys, tmp, "bad_targets.csv", expected)
    _fails(["calibrate", pulses, "--targets", tmp / "bad_targets.csv", "--datasets", tmp / "datasets.csv",
            "--out", tmp / "S.parquet", "--json", tmp / "S.json"], capsys, tmp, "bad_targets.csv", expected)


def test_header_only_targets(campaign, capsys):
    tmp, pulses = campaign
    (tmp / "empty_targets.csv").write_text(",".join(TARGET) + "\n")
    _fails(_agc(tmp, pulses, targets="empty_targets.csv"), capsys, tmp, "empty_targets.csv", "no rows")


def test_header_only_fields_and_datasets(campaign, capsys):
    tmp, pulses = campaign
    (tmp / "empty_fields.csv").write_text(",".join(FIELD) + "\n")
    _fails(_select(tmp, pulses, fields="empty_fields.csv"), capsys, tmp, "empty_fields.csv", "no rows")
    (tmp / "empty_datasets.csv").write_text(",".join(DATASET) + "\n")
    _fails(_select(tmp, pulses, datasets="empty_datasets.csv"), capsys, tmp, "empty_datasets.csv", "no rows")


@pytest.mark.parametrize("value", ["-3", "0"])
def test_threads_below_one(campaign, capsys, value):
    tmp, pulses = campaign
    _fails(_select(tmp, pulses, "fields.csv", "datasets.csv", "--threads", value), capsys, tmp,
           "--threads", f"{value} is not in the range x>=1")


def test_unknown_simulate_species_in_the_config(campaign, capsys):
    tmp, pulses = campaign
    cfg = tmp / "oak.yaml"
    cfg.write_text("simulate:\n  species: [birch, oak]\n")
    for argv in (_select(tmp, pulses, "fields.csv", "datasets.csv", "--config", cfg),
                 ["compare", "--real", pulses, "--sim", pulses, "--pulses-real", pulses, "--pulses-sim", pulses,
                  "--out", tmp / "cmp", "--config", cfg]):
        _fails(argv, capsys, tmp, "oak.yaml: simulate/species: unknown species 'oak'", "birch, european_aspen")


def test_misspelled_nested_config_key(campaign, capsys):
    tmp, pulses = campaign
    cfg = tmp / "typo.yaml"
    cfg.write_text("mcrt:\n  n_rayz: 5\n")
    _fails(_select(tmp, pulses, "fields.csv", "datasets.csv", "--config", cfg), capsys, tmp,
           "typo.yaml: mcrt/n_rayz: unknown key", "n_rays")


def test_valid_tables_pass(campaign):
    """The fixture's tables are valid: the failures above come from the one bad value."""
    from waveforest.io.tables import read_datasets, read_fields, read_targets

    tmp, _ = campaign
    assert len(read_datasets(tmp / "datasets.csv")) == len(read_fields(tmp / "fields.csv")) == 1
    assert read_targets(tmp / "targets.csv")["hdrf"].iloc[0] == pytest.approx(0.34)
