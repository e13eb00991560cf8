"""io/results.py: each pipeline table has one reader and one writer, with checks."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from waveforest.atomic import plain
from waveforest.errors import WaveforestError
from waveforest.io import results
from waveforest.io.pulses import PULSE_SCHEMA, single_dataset


def test_plain_converts_numpy_and_non_finite_values():
    v = {np.int64(4): (np.float32(0.5), np.nan, np.inf), "a": np.arange(3), "b": np.bool_(True)}
    assert plain(v) == {"4": [0.5, None, None], "a": [0, 1, 2], "b": True}
    assert plain(v, keep_inf=True)["4"] == [0.5, None, float("inf")]


def test_feature_tables_round_trip_and_errors(tmp_path):
    df = pd.DataFrame({"dataset": ["d", "d"], "pulse_id": [1, 2], "Apeak": [1.5, np.nan]})
    results.write_feature_table(df, tmp_path / "f.parquet")
    back = results.read_feature_tables([tmp_path / "f.parquet", tmp_path / "f.parquet"])
    assert len(back) == 4 and list(back.columns) == list(df.columns)
    with pytest.raises(WaveforestError, match="no such file"):
        results.read_feature_tables([tmp_path / "nope.parquet"])
    with pytest.raises(WaveforestError, match="no feature table"):
        results.read_feature_tables([])
    sel = pd.DataFrame({"dataset": ["d", "d"], "pulse_id": [1, 2], "species": ["birch", "sand"]})
    assert list(results.attach_selection(back.iloc[:2], sel)["species"]) == ["birch", "sand"]


def test_select_columns_and_select_table_checks(tmp_path):
    t = pa.table({"dataset": ["d"], "pulse_id": [1], "species": ["birch"]})
    pq.write_table(t, tmp_path / "s.parquet")
    got = results.read_select_columns([tmp_path / "s.parquet"], ["dataset", "pulse_id", "comparison_set"])
    assert list(got.columns) == ["dataset", "pulse_id"]
    with pytest.raises(WaveforestError, match="not a select table: no column"):
        results.read_select_columns([tmp_path / "s.parquet"], ["dataset"], required=("n_echoes",))
    (tmp_path / "bad.parquet").write_text("x")
    with pytest.raises(WaveforestError, match="not a readable Parquet"):
        results.read_select_columns([tmp_path / "bad.parquet"], ["dataset"])
    empty = PULSE_SCHEMA.empty_table()
    pq.write_table(empty, tmp_path / "p.parquet")
    with pytest.raises(WaveforestError, match="not a select table"):
        results.read_select_table(tmp_path / "p.parquet")


def test_json_documents_round_trip_and_errors(tmp_path):
    results.write_classify_result({"main": {}, "x": np.float64(1.0)}, tmp_path / "2012_10_1.json")
    assert results.read_classify_result(tmp_path / "2012_10_1.json") == {"main": {}, "x": 1.0, "dataset": "2012_10_1"}
    results.write_calibration_json({"dataset": "d", "noise_mean": 10.0, "noise_sd": None}, tmp_path / "c.json")
    with pytest.raises(WaveforestError, match="calibration lacks noise_sd"):
        results.read_calibration_json(tmp_path / "c.json")
    assert results.read_calibration_json(tmp_path / "c.json", required=())["noise_mean"] == 10.0
    (tmp_path / "bad.json").write_text("[1, 2]")
    with pytest.raises(WaveforestError, match="not a JSON object"):
        results.read_agc_fit(tmp_path / "bad.json")
    (tmp_path / "worse.json").write_text("{")
    with pytest.raises(WaveforestError, match="not valid JSON"):
        results.read_classify_result(tmp_path / "worse.json")


def test_agc_metadata_round_trip(tmp_path):
    t = pa.table({"x": [1]}).replace_schema_metadata(results.agc_schema_metadata("d", 1.0, 0.01, 10.0))
    pq.write_table(t, tmp_path / "n.parquet")
    assert results.read_agc_metadata(tmp_path / "n.parquet") == {"dataset": "d", "a": 1.0, "b": 0.01, "n0": 10.0}
    pq.write_table(pa.table({"x": [1]}), tmp_path / "plain.parquet")
    assert results.read_agc_metadata(tmp_path / "plain.parquet") == {}


def test_system_waveform_table_round_trip(tmp_path):
    t = np.arange(4) * 0.05
    results.write_system_waveform_table(t, np.ones(4), np.full(4, np.nan), {"fwhm_ns": np.float64(7.0)},
                                        tmp_path / "s.parquet")
    t2, s2, sd, meta = results.read_system_waveform_table(tmp_path / "s.parquet")
    assert np.array_equal(t, t2) and np.array_equal(s2, np.ones(4)) and sd is None and meta == {"fwhm_ns": 7.0}
    pq.write_table(pa.table({"t_ns": t}), tmp_path / "bad.parquet")
    with pytest.raises(WaveforestError, match="lacks column"):
        results.read_system_waveform_table(tmp_path / "bad.parquet")


def test_model_yaml_reader_rejects_bad_files(tmp_path):
    (tmp_path / "m.yaml").write_text("effects: {understory: 1.2}\n")
    with pytest.raises(WaveforestError, match="verdict"):
        results.read_model(tmp_path / "m.yaml")
    (tmp_path / "y.yaml").write_text("verdict: [\n")
    with pytest.raises(WaveforestError, match="not valid YAML"):
        results.read_model(tmp_path / "y.yaml")
    p = results.write_model(tmp_path / "ok.yaml", results.model_dict("none", [], reason="no gap"))
    assert results.read_model(p)["effects_dict"] == {}
    assert json.loads(json.dumps(results.read_model(p)))["verdict"] == "none"


def test_single_dataset():
    assert single_dataset({"d"}, "p") == "d"
    with pytest.raises(WaveforestError, match="expected exactly one"):
        single_dataset({"a", "b"}, "p")
