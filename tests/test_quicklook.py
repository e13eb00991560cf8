"""``quicklook`` end to end on the bundled real RIEGL file through the CLI, and ``features --cfd``."""

from __future__ import annotations

import json
import re

import numpy as np
import pyarrow.parquet as pq
import pytest
from fixtures.real import quicklook_of_riegl
from reference_io import RIEGL
from test_laz import assert_tables_identical

from waveforest.cli import main
from waveforest.constants import RANGE_PER_NS
from waveforest.io.las import summarise
from waveforest.report.quicklook import detect_afterpulse, fmt


@pytest.fixture(scope="module")
def looked(tmp_path_factory):
    return quicklook_of_riegl(tmp_path_factory.mktemp("ql"))[1]


def test_quicklook_writes_every_output(looked, capsys):
    names = sorted(p.name for p in looked.iterdir() if p.name != ".waveforest")  # beside the folder's manifest
    assert names == ["cfd.json", "cfd.png", "features.parquet", "pulses.parquet", "quicklook.html"]  # no temporaries
    page = (looked / "quicklook.html").read_text()
    # maps, CFD, gallery, decomposition, histograms, map
    assert len(re.findall(r'<img src="data:image/png;base64,', page)) == 6
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


def _facts(page: str) -> dict[str, str]:
    import html

    return {html.unescape(k): html.unescape(v) for k, v in re.findall(r"<tr><th>(.*?)</th><td>(.*?)</td></tr>", page)}


def test_quicklook_header_block(looked):
    """The header block on the bundled RIEGL file, against laspy's own reading of its points."""
    laspy = pytest.importorskip("laspy")
    las = laspy.read(RIEGL)
    z = np.asarray(las.z)
    facts = _facts((looked / "quicklook.html").read_text())
    assert facts["format"].startswith("LAS 1.4, point format 9; waveform packets external (riegl_fwf.wdp)")
    assert facts["coordinate system"] == "UTM_North zone 33 (no EPSG code; WKT VLR)"
    assert facts["points / pulses"] == "2,535 points in 2,368 pulses"
    assert facts["returns per pulse"] == "1 return: 2,209; 2 returns: 151; 3 returns: 8"
    assert facts["classification"] == "ground (2): 2,251; medium vegetation (4): 284"
    # z: 234.6-509.7 m with 3 outliers (the canopy over its ground, 354-366 m, is not flagged)
    p1, p99 = np.percentile(z, [1, 99])
    d = max(p99 - p1, 10.0)
    n_out = int(np.sum((z < p1 - d) | (z > p99 + d)))
    assert n_out == 3
    assert facts["z range"].startswith("234.6 m .. 509.7 m; 3 outliers outside 343.7 m .. 376.2 m (rule: ")
    assert facts["scan angle"] == "85.0° .. 87.0°"
    assert facts["sampling"] == "1.00 ns"
    assert facts["GPS time"].endswith("(span 0.5 s)")
    assert facts["extent (x, y)"] == "548342.7 m .. 548369.6 m, 5389930.0 m .. 5389957.7 m (26.8 m × 27.8 m)"
    assert facts["point density"].startswith("points 6.7 per m², pulses 6.3 per m², over the 377 m² covered")
    assert re.fullmatch(r"4\.\d\d DN ± 1\.\d\d DN \(mean ± SD\)", facts["noise (last samples)"])
    assert facts["system pulse FWHM"].startswith("4.41 ns (tuned CFD")


def test_las_summary_counts_agree_with_laspy():
    laspy = pytest.importorskip("laspy")
    las = laspy.read(RIEGL)
    s = summarise(RIEGL)
    assert dict(s.classes) == dict(zip(*np.unique(np.asarray(las.classification), return_counts=True)))
    assert sum(k * v for k, v in s.points_per_pulse.items()) == s.n_points == len(las.points)
    assert s.n_z_outliers == 3 and s.grid.count.sum() == s.n_points
    assert np.nanmax(s.grid.top_z) < s.z_window[1]  # outliers left out of the elevation map
    assert s.scan_range == pytest.approx((85.002, 87.0))


def test_quicklook_notes_the_afterpulse(looked):
    """RIEGL: a second CFD echo ~11 ns after the main one in most single-target pulses."""
    res = json.loads((looked / "cfd.json").read_text())
    after = detect_afterpulse(looked / "features.parquet", res["system_fwhm_ns"])
    assert after is not None and 10.0 < after.delay_ns < 11.5 and after.sd_ns < 1.0
    assert after.n_single == 2209 and after.share > 0.5
    page = (looked / "quicklook.html").read_text()
    assert "The file shows an afterpulse" in page and f"a second echo {fmt(after.delay_ns, 'ns')} after" in page


def test_no_afterpulse_without_a_constant_delay(tmp_path):
    """Second echoes at spread delays (second targets) are not an afterpulse."""
    import pyarrow as pa
    import pyarrow.parquet as pq_

    rng = np.random.default_rng(3)
    n = 400
    first = rng.uniform(20, 30, n)
    second = first + rng.uniform(6, 60, n)
    t = pa.table({"n_echoes": pa.array(np.ones(n, np.int64)),
                  "cfd_time_ns": pa.array([[a, b] for a, b in zip(first, second)], pa.list_(pa.float64()))})
    pq_.write_table(t, tmp_path / "f.parquet")
    assert detect_afterpulse(tmp_path / "f.parquet", 4.0) is None
    constant = pa.table({"n_echoes": t.column("n_echoes"),
                         "cfd_time_ns": pa.array([[a, a + 9.0 + 0.1 * rng.standard_normal()] for a in first],
                                                 pa.list_(pa.float64()))})
    pq_.write_table(constant, tmp_path / "g.parquet")
    found = detect_afterpulse(tmp_path / "g.parquet", 4.0)
    assert found is not None and found.delay_ns == pytest.approx(9.0, abs=0.1) and found.n == n


def test_one_rounding_rule(looked):
    assert fmt(-0.0004, "cm") == "0.0 cm" and fmt(-0.04, "cm") == "0.0 cm" and fmt(-0.06, "cm") == "-0.1 cm"
    assert fmt(0.97973, "%") == "98.0 %" and fmt(2368) == "2,368" and fmt(None, "m") == "n/a"
    assert fmt(float("nan"), "ns") == "n/a" and fmt(548342.742, "m", grouped=False) == "548342.7 m"
    assert fmt(86.9999, "deg") == "87.0°"
    page = (looked / "quicklook.html").read_text()
    text = re.sub(r"<[^>]+>", " ", re.sub(r'src="[^"]+"', "", page))
    assert not re.search(r"(?<!\w)-0(\.0+)?(?!\d)", text)  # no negative zero anywhere (pytest-0 in a path is no number)
    facts = _facts(page)
    assert facts["median residual"] == "0.0 cm"  # -0.04 cm rounds to the page's 0.1 cm


def test_quicklook_shows_the_decomposition(looked):
    """The echoes-per-pulse chart and profile come from decomposing the file's own pulses: on the
    RIEGL file most pulses hold two echoes (the return and its afterpulse, ~11 ns later)."""
    from waveforest.report.quicklook import decomposition_sample

    page = (looked / "quicklook.html").read_text()
    assert "Echoes of the Gaussian decomposition" in page and 'alt="echoes per pulse and a profile' in page
    res = json.loads((looked / "cfd.json").read_text())
    counts, xyz = decomposition_sample(looked / "pulses.parquet", res, seed=7)
    assert counts.sum() == 2368 and int(np.argmax(counts)) == 2
    assert len(xyz) == int((np.arange(len(counts)) * counts).sum()) and np.isfinite(xyz).all()


@pytest.mark.parametrize("p_true", [0.0005, 0.3, 0.999])
def test_gallery_draws_the_same_pulses_without_an_index_of_every_pulse(p_true):
    """nth_true picks the ranked true elements, so drawing ranks picks what rng.choice on the index array picked."""
    from waveforest.report.quicklook import nth_true

    mask = np.random.default_rng(3).random(2_500_007) < p_true
    idx = np.flatnonzero(mask)
    for seed in range(3):
        k = min(len(idx), 7)
        old = np.random.default_rng(seed).choice(idx, size=k, replace=False)
        new = nth_true(mask, np.random.default_rng(seed).choice(len(idx), size=k, replace=False), chunk=100_003)
        np.testing.assert_array_equal(new, old)
    with pytest.raises(IndexError):
        nth_true(mask, np.array([len(idx)]))
