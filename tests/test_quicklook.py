"""``quicklook`` end to end on the bundled real RIEGL file through the CLI, and ``features --cfd``."""

from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pyarrow.parquet as pq
import pytest
from reference_io import RIEGL
from test_laz import assert_tables_identical

from waveforest.cli import main
from waveforest.constants import RANGE_PER_NS


@pytest.fixture(scope="module")
def looked(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ql")
    shutil.copy(RIEGL, tmp / RIEGL.name)
    shutil.copy(RIEGL.with_suffix(".wdp"), tmp / RIEGL.with_suffix(".wdp").name)
    out = tmp / "look"
    main(["quicklook", str(tmp / RIEGL.name), "--out", str(out), "--no-progress"])
    return out


def test_quicklook_writes_every_output(looked, capsys):
    names = sorted(p.name for p in looked.iterdir())
    assert names == ["cfd.json", "cfd.png", "features.parquet", "pulses.parquet", "quicklook.html"]  # no temporaries
    page = (looked / "quicklook.html").read_text()
    assert len(re.findall(r'<img src="data:image/png;base64,', page)) == 4  # CFD, gallery, histograms, map
    assert "within 0.10 m" in page and "criterion met" in page and "riegl_fwf.las" in page


def test_quicklook_check_agrees_with_its_feature_table(looked):
    """The share in cfd.json, recomputed from the written CFD echoes and DR echoes: over all pulses
    with a DR echo, first CFD echo (range-corrected) within 0.10 m of the first DR echo."""
    res = json.loads((looked / "cfd.json").read_text())
    f = pq.read_table(looked / "features.parquet")
    pulses = pq.read_table(looked / "pulses.parquet", columns=["pulse_id", "echo_time_ns"])
    assert f.num_rows == pulses.num_rows == res["n_pulses_total"] == 2368
    np.testing.assert_array_equal(f.column("pulse_id").to_numpy(), pulses.column("pulse_id").to_numpy())
    dr = np.array([v[0] if v else np.nan for v in pulses.column("echo_time_ns").to_pylist()])
    cfd = np.array([v[0] if v else np.nan for v in f.column("cfd_time_ns").to_pylist()])
    has = np.isfinite(dr)
    share = np.mean(np.abs((dr[has] - cfd[has]) * RANGE_PER_NS) < 0.10)
    assert share == pytest.approx(res["within_0_10_m"], abs=1e-12)
    assert res["within_0_10_m"] >= 0.95 and abs(res["median_residual_m"]) < 0.02
    # every CFD echo's position lies on its beam at its time: z from the anchor
    z = f.column("cfd_z").to_pylist()
    t = f.column("cfd_time_ns").to_pylist()
    assert all(len(a) == len(b) == n for a, b, n in zip(z, t, f.column("n_cfd_echoes").to_pylist()))


def test_features_needs_exactly_one_of_calibration_and_cfd(looked, tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["features", str(looked / "pulses.parquet"), "--out", str(tmp_path / "f.parquet")])
    assert exc.value.code == 2
    assert "either --calibration" in capsys.readouterr().err
    assert not (tmp_path / "f.parquet").exists()


def test_features_with_cfd_alone(looked, tmp_path, capsys):
    out = tmp_path / "f.parquet"
    main(["features", str(looked / "pulses.parquet"), "--cfd", str(looked / "cfd.json"), "--out", str(out),
          "--no-progress"])
    assert "2,368 pulses" in capsys.readouterr().out
    a, b = pq.read_table(out), pq.read_table(looked / "features.parquet")
    assert_tables_identical(a, b)  # the same table as quicklook's
    for c in ("Apeak", "FWHM", "E", "Npeaks", "echo_x", "echo_y", "echo_z", "cfd_time_ns", "cfd_range_m",
              "cfd_x", "cfd_y", "cfd_z", "cfd_amplitude"):
        assert c in a.column_names
    assert np.isfinite(a.column("Apeak").to_numpy()).all()  # every pulse has a first-echo segment
