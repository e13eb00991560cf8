"""Gaussian decomposition (``waveforest.sensor.decompose``) and the ``decompose`` command."""

from __future__ import annotations

import json
import math
import shutil

import laspy
import numpy as np
import pyarrow as pa
import pytest
from fixtures.real import RIEGL

from waveforest.cli import main
from waveforest.io.las.extra_bytes import ECHO_DIMENSIONS
from waveforest.model.decompose import DecomposeSettings, echo_columns
from waveforest.sensor.decompose import (
    AMP_BOUND,
    FLAG_CLIPPED,
    FLAG_FLAT,
    FLAG_NOISE,
    FLAG_NOT_CONVERGED,
    FLAG_POOR_FIT,
    FLAG_SHORT,
    decompose,
)

SD = 1.3
FWHM = 7.0
S = FWHM / (2 * math.sqrt(2 * math.log(2)))


def _waveforms(echoes, n_samples=160, dt=1.0, noise=SD, seed=0, mean=10.0):
    """Waveforms (n, n_samples) from per-row lists of (A, mu) Gaussians of SD ``S``, plus noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(n_samples) * dt
    x = mean + rng.normal(0.0, noise, (len(echoes), n_samples)) if noise else np.full((len(echoes), n_samples), mean)
    for i, row in enumerate(echoes):
        for a, mu in row:
            x[i] += a * np.exp(-0.5 * ((t - mu) / S) ** 2)
    return x


def test_a_noise_free_echo_is_recovered_exactly():
    x = _waveforms([[(40.0, 61.3)], [(25.0, 30.7), (12.0, 90.2)]], noise=0.0)
    d = decompose(x, None, 1.0, 10.0, SD)
    assert list(d.n_echoes) == [1, 2]
    np.testing.assert_allclose(d.time_ns[0, :1], [61.3], atol=1e-3)
    np.testing.assert_allclose(d.amplitude[1, :2], [25.0, 12.0], rtol=1e-3)
    np.testing.assert_allclose(d.sigma_ns[1, :2], [S, S], rtol=1e-3)
    # energy is the echo's area: the waveform's integral above the noise mean
    np.testing.assert_allclose(np.nansum(d.energy[1]), (x[1] - 10.0).sum(), rtol=1e-3)
    assert np.isnan(d.time_ns[0, 1:]).all() and not np.isnan(d.time_ns[1, :2]).any()


def test_recall_and_precision_for_echoes_of_5_sd_one_pulse_width_apart():
    """Echoes >= 5 noise SD separated by >= 1 FWHM: recall and precision >= 0.95 (issue target)."""
    rng = np.random.default_rng(7)
    rows = []
    for _ in range(400):
        k = int(rng.integers(1, 4))
        mus = 20.0 + np.cumsum(rng.uniform(FWHM, 3 * FWHM, k))
        rows.append([(float(rng.uniform(5, 40) * SD), float(m)) for m in mus])
    d = decompose(_waveforms(rows, seed=8), None, 1.0, 10.0, SD, pulse_fwhm_ns=FWHM)
    hit = found = true = 0
    for i, row in enumerate(rows):
        t = d.time_ns[i, : d.n_echoes[i]]
        found += len(t)
        true += len(row)
        hit += sum(np.min(np.abs(t - mu), initial=np.inf) < S for _, mu in row)
    assert hit / true >= 0.95 and hit / found >= 0.95, (hit, true, found)


def test_pure_noise_gives_no_echo_in_nearly_every_waveform():
    d = decompose(_waveforms([[]] * 500, seed=3), None, 1.0, 10.0, SD, pulse_fwhm_ns=FWHM)
    assert np.mean(d.n_echoes == 0) >= 0.95
    assert np.all(d.flags[d.n_echoes == 0] & FLAG_NOISE)


def test_bad_waveforms_are_flagged_and_never_nan():
    x = np.full((4, 64), np.nan, np.float32)
    x[0, :] = 10.0  # flat
    x[1, :3] = [10, 40, 10]  # too short
    x[2, :] = np.round(_waveforms([[(400.0, 30.0)]], n_samples=64)[0])
    x[2] = np.minimum(x[2], 255.0)  # an 8-bit digitiser clipped
    x[3, :] = _waveforms([[]], n_samples=64, seed=5)[0]
    lens = np.array([64, 3, 64, 64])
    d = decompose(x, lens, 1.0, 10.0, SD, pulse_fwhm_ns=FWHM)
    assert d.flags[0] & FLAG_FLAT and d.n_echoes[0] == 0
    assert d.flags[1] & FLAG_SHORT and d.n_echoes[1] == 0
    assert d.flags[2] & FLAG_CLIPPED and d.n_echoes[2] == 1
    assert abs(d.time_ns[2, 0] - 30.0) < 0.5  # the clipped top is left out, the flanks place the echo
    for i in range(4):
        k = d.n_echoes[i]
        assert np.isfinite(d.time_ns[i, :k]).all() and np.isfinite(d.amplitude[i, :k]).all()


def test_equal_top_samples_are_clipped_only_at_full_scale():
    """An integer echo whose peak lies midway between two samples, or a wide echo with a flat top,
    holds its maximum over several samples: not clipped (its top keeps its weight); held at 255
    (8-bit) or 4095 (12-bit) it is."""
    x = np.round(_waveforms([[(a, 60.5)] for a in (20.0, 45.0, 80.0, 150.0)], noise=0.0))
    x = np.vstack([x, np.round(_waveforms([[(60.0, 58.0), (60.0, 63.0)]], noise=0.0))])  # a flat-topped pair
    assert all((row == row.max()).sum() >= 2 for row in x)
    d = decompose(x, None, 1.0, 10.0, SD, pulse_fwhm_ns=FWHM)
    assert not np.any(d.flags & FLAG_CLIPPED) and np.all(d.n_echoes[:4] == 1)
    np.testing.assert_allclose(d.time_ns[:4, 0], 60.5, atol=0.05)
    full = np.round(_waveforms([[(260.0, 60.5)], [(5000.0, 60.5)]], noise=0.0))
    full[0], full[1] = np.minimum(full[0], 255.0), np.minimum(full[1], 4095.0)
    assert full[0, 60] == full[0, 61] == 255 and full[1, 60] == full[1, 61] == 4095
    assert np.all(decompose(full, None, 1.0, 10.0, SD, pulse_fwhm_ns=FWHM).flags & FLAG_CLIPPED)


def test_a_clipped_record_is_found_after_agc_normalisation():
    """AGC-normalised samples ((V - n0) / g + n0, Eq. 1) of a record clipped at 255: with its gain
    the top is found clipped and left out, and the echo's amplitude is the unclipped one's / g."""
    g, true_a = 1.6, 400.0
    raw = np.minimum(np.round(_waveforms([[(true_a, 60.5)]], noise=0.0)), 255.0)
    norm = (raw - 10.0) / g + 10.0
    plain = decompose(norm, None, 1.0, 10.0, SD, pulse_fwhm_ns=FWHM)
    d = decompose(norm, None, 1.0, 10.0, SD, pulse_fwhm_ns=FWHM, agc_gain=g)
    assert not plain.flags[0] & FLAG_CLIPPED and d.flags[0] & FLAG_CLIPPED
    assert abs(d.amplitude[0, 0] / (true_a / g) - 1) < 0.02 < abs(plain.amplitude[0, 0] / (true_a / g) - 1)


RIEGL_CFD = {"noise_mean": 4.105967, "noise_sd": 1.171688, "pulse_fwhm_ns": 4.41234419178228}
"""Noise and system pulse of the RIEGL file (`waveforest quicklook`'s cfd.json)."""
RIEGL_1677 = [3, 4, 3, 4, 4, 4, 3, 3, 2, 2, 2, 2, 2, 2, 3, 14, 41, 92, 143, 170, 155, 106, 56, 24, 13, 10, 8, 7, 8, 10,
              12, 10, 8, 8, 7, 7, 7, 7, 7, 5, 5, 4, 4, 5, 5, 5, 5, 4, 5, 5, 4, 4, 3, 4, 3, 4, 4, 4, 4, 4]
RIEGL_122 = [2, 2, 3, 3, 2, 3, 2, 3, 3, 3, 2, 4, 8, 28, 71, 136, 192, 213, 183, 122, 64, 32, 19, 15, 13, 12, 12, 14, 14,
             14, 11, 10, 10, 9, 8, 9, 8, 8, 8, 7, 7, 7, 7, 8, 8, 9, 9, 8, 6, 6, 5, 6, 5, 7, 6, 5, 5, 4, 3, 5]
"""Samples (DN, 1 ns) of two pulses of the RIEGL file: one echo and its afterpulse; one echo with a long tail."""


def _riegl(samples, **kw):
    c = RIEGL_CFD
    return decompose(np.array([samples], float), None, 1.0, c["noise_mean"], c["noise_sd"],
                     pulse_fwhm_ns=c["pulse_fwhm_ns"], **kw)


def test_no_phantom_echo_at_the_records_edge():
    """A component that leaves the fitted samples is free of the data: it must stay inside
    them, its amplitude bounded by the data (RIEGL pulse 1677 gave an echo at 0 ns of 1106 DN)."""
    d = _riegl(RIEGL_1677)
    k = d.n_echoes[0]
    assert k == 2 and d.flags[0] == 0
    np.testing.assert_allclose(d.time_ns[0, :k], [19.15, 30.2], atol=0.5)
    assert d.amplitude[0, 0] == pytest.approx(170 - RIEGL_CFD["noise_mean"], rel=0.03)
    assert d.rms_residual[0] < 3.0


def test_an_added_component_that_does_not_survive_leaves_the_fit_before_it():
    """RIEGL pulse 122: the tail's component merges into the echo; the echo must stay the fitted
    one (209 DN, SD 1.96 ns), not the unfitted merge (109 DN, SD 4.3 ns, flagged not converged)."""
    d = _riegl(RIEGL_122)
    assert d.n_echoes[0] == 1 and not d.flags[0] & (FLAG_NOT_CONVERGED | FLAG_POOR_FIT)
    assert d.amplitude[0, 0] == pytest.approx(213 - RIEGL_CFD["noise_mean"], rel=0.03)
    assert d.sigma_ns[0, 0] == pytest.approx(1.96, abs=0.1) and d.rms_residual[0] < 6.0


def test_echoes_stay_inside_the_record_and_below_the_amplitude_bound():
    rng = np.random.default_rng(11)
    rows = [[(float(rng.uniform(3, 60) * SD), float(rng.uniform(-5, 70))) for _ in range(rng.integers(0, 5))]
            for _ in range(1500)]
    x = _waveforms(rows, n_samples=64, seed=12)
    d = decompose(x, None, 1.0, 10.0, SD, pulse_fwhm_ns=FWHM)
    has = np.arange(d.time_ns.shape[1]) < d.n_echoes[:, None]
    peak = np.max(x, axis=1) - 10.0
    assert np.all((d.time_ns[has] >= 0.0) & (d.time_ns[has] <= 63.0))
    assert np.all(d.amplitude <= (AMP_BOUND * peak + 3.0 * SD)[:, None] + 1e-9, where=has)


def test_a_fit_far_from_the_data_is_flagged_poor_and_keeps_its_echo():
    x = np.full((1, 80), 10.0)
    x[0, 20:50] = 110.0  # a flat-topped return no Gaussian of the system pulse's width fits
    d = decompose(x, None, 1.0, 10.0, SD, pulse_fwhm_ns=FWHM, fixed_width=True, max_echoes=1)
    assert d.n_echoes[0] == 1 and d.flags[0] & FLAG_POOR_FIT
    assert not _riegl(RIEGL_1677).flags[0] & FLAG_POOR_FIT


def test_each_point_carries_its_pulses_flags():
    """echo_columns: every echo of a pulse has the pulse's flags (a not-converged or poor fit
    keeps its echoes, marked)."""
    d = _riegl(RIEGL_1677)
    d = d._replace(flags=np.array([FLAG_NOT_CONVERGED | FLAG_POOR_FIT], np.uint8))
    cols = {f"{c}_{a}": [0.0] for c in ("anchor", "dir", "sensor") for a in "xyz"}
    batch = pa.table({**cols, "gps_time": [1.0], "scan_angle_deg": [0.0], "pulse_id": [0]})
    out = echo_columns(batch, d, DecomposeSettings(), 0)
    assert list(out["flags"]) == [FLAG_NOT_CONVERGED | FLAG_POOR_FIT] * 2


def test_the_point_cloud_marks_the_points_of_suspect_fits(tmp_path):
    out = tmp_path / "e.las"
    main(["decompose", str(RIEGL), "--out", str(out), "--nominal-range", "1000", "--no-progress"])
    las = laspy.read(out)
    summary = json.loads((tmp_path / "e.las.json").read_text())
    flags, pid = np.asarray(las["flags"]), np.asarray(las.pulse_id)
    assert summary["flagged_pulses"].get("poor fit", 0) > 0  # free widths: two echoes fitted as one
    for bit, name in ((FLAG_CLIPPED, "clipped"), (FLAG_NOT_CONVERGED, "fit not converged"), (FLAG_POOR_FIT, "poor fit")):
        assert len(np.unique(pid[(flags & bit) > 0])) == summary["flagged_pulses"].get(name, 0), name
    for p in np.unique(pid):  # one value per pulse
        assert np.ptp(flags[pid == p]) == 0


def test_fixed_width_keeps_the_system_pulse_width():
    x = _waveforms([[(30.0, 50.0), (20.0, 75.0)]], seed=2)
    d = decompose(x, None, 1.0, 10.0, SD, pulse_fwhm_ns=FWHM, fixed_width=True)
    assert d.n_echoes[0] == 2
    np.testing.assert_allclose(d.sigma_ns[0, :2], S, rtol=1e-12)


def test_decompose_command_writes_a_point_cloud_laspy_reads(tmp_path, capsys):
    out = tmp_path / "echoes.laz"
    main(["decompose", str(RIEGL), "--out", str(out), "--nominal-range", "1000", "--no-progress"])
    summary = json.loads((tmp_path / "echoes.laz.json").read_text())
    las = laspy.read(out)
    assert (las.header.version.major, las.header.version.minor, las.header.point_format.id) == (1, 4, 6)
    assert list(las.point_format.extra_dimension_names) == [n for n, _, _ in ECHO_DIMENSIONS]
    assert len(las.points) == summary["n_echoes"] > summary["n_pulses"] == 2368
    assert sum(summary["echoes_per_pulse"].values()) + summary["flagged_pulses"].get("all noise", 0) >= 2368 - 5
    # the echoes lie on their beams about 1000 m from the sensor, numbered in time order
    assert np.all(np.abs(np.asarray(las.range_m) - 1000.0) < 20.0)
    first = np.asarray(las.return_number) == 1
    assert first.sum() == len(np.unique(np.asarray(las.pulse_id)))
    assert np.all(np.asarray(las.amplitude_dn) > 0) and np.isfinite(np.asarray(las.energy_dn_ns)).all()
    # the relative cross-section follows Eq. F2
    r, a, s = (np.asarray(las[k], np.float64) for k in ("range_m", "amplitude_dn", "sigma_ns"))
    np.testing.assert_allclose(las.cross_section, (r / 1000.0) ** 4 * a * s, rtol=1e-5)
    # every pulse's echoes are numbered 1..n along the beam, n its points
    pid, ret, nret = (np.asarray(las[k]) for k in ("pulse_id", "return_number", "number_of_returns"))
    for p in np.unique(pid):
        m = pid == p
        assert sorted(ret[m]) == list(range(1, m.sum() + 1)) and np.all(nret[m] == m.sum())
    # 7 pulses hold their returns in two packets (RIEGL's segments): both are decomposed, so every
    # return the scanner recorded in a second packet has an echo of the cloud within 10 cm
    assert summary["n_pulses_several_packets"] == 7 and summary["n_packets"] == 2375
    assert "7 with returns in several waveform packets, each decomposed" in capsys.readouterr().out
    src = laspy.read(RIEGL)
    g, off = np.asarray(src.gps_time), np.asarray(src.wavepacket_offset)
    sxyz = np.column_stack([src.x, src.y, src.z])
    first_off = {t: off[g == t][np.argmin(np.asarray(src.return_number)[g == t])] for t in np.unique(g)}
    later = np.flatnonzero([off[i] != first_off[g[i]] for i in range(len(g))])
    assert len(later) == 7
    xyz, gps = np.column_stack([las.x, las.y, las.z]), np.asarray(las.gps_time)
    for i in later:
        near = np.linalg.norm(xyz[gps == g[i]] - sxyz[i], axis=1)
        assert near.min() < 0.10, (g[i], near)
    main(["info", str(out)])
    said = capsys.readouterr().out
    assert "point format 6 (no waveforms)" in said and "extra bytes cross_section" in said
    assert "UTM_North zone 33" in said  # the source file's coordinate system is carried over


def _by_gps(table):
    """gps time -> row of a pulse table."""
    return {float(g): i for i, g in enumerate(table.column("gps_time").to_numpy())}


def _check_waveforms_kept(src_table, out):
    """The PF9 cloud ``out``: each echo's packet is its source pulse's, its return point location is its time."""
    from waveforest.constants import RANGE_PER_NS
    from waveforest.io.las import read_waveform_las
    from waveforest.io.pulses import list_to_padded

    las = laspy.read(out)
    assert (las.header.point_format.id, las.header.global_encoding.waveform_data_packets_external) == (9, True)
    assert list(las.point_format.extra_dimension_names) == [n for n, _, _ in ECHO_DIMENSIONS]
    # the return point location is the echo's time after the first sample, and x(t), y(t), z(t) c/2 per ps
    np.testing.assert_allclose(np.asarray(las.return_point_wave_location) / 1000.0, las.echo_time_ns, rtol=1e-6)
    d = np.stack([np.asarray(las[k], np.float64) for k in ("x_t", "y_t", "z_t")], 1)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), RANGE_PER_NS / 1000.0, rtol=1e-6)
    back = read_waveform_las(out, agc_attribute=None)
    assert back.num_rows == len(np.unique(np.asarray(las.gps_time)))
    src_row, row = _by_gps(src_table), _by_gps(back)
    xs, ls = list_to_padded(src_table.column("samples"))
    xb, lb = list_to_padded(back.column("samples"))
    i = np.array([src_row[g] for g in row])
    j = np.array(list(row.values()))
    np.testing.assert_array_equal(lb[j], ls[i])
    np.testing.assert_array_equal(xb[j], xs[i][:, : xb.shape[1]])
    for c in ("sampling_ns", "dir_x", "dir_y", "dir_z"):
        np.testing.assert_allclose(back.column(c).to_numpy()[j], src_table.column(c).to_numpy()[i], atol=1e-4)
    for a in "xyz":  # the first sample's position, from the quantised points (scale 1 mm)
        np.testing.assert_allclose(back.column(f"anchor_{a}").to_numpy()[j], src_table.column(f"anchor_{a}").to_numpy()[i],
                                   atol=2e-3)
    # each echo's time read back reproduces its range: range - t c/2 is the range of its packet's
    # first sample, one per packet
    first_sample = np.asarray(las.range_m, np.float64) - np.asarray(las.echo_time_ns, np.float64) * RANGE_PER_NS
    packet = np.unique(np.column_stack([las.pulse_id, las.wavepacket_offset]), axis=0, return_inverse=True)[1].ravel()
    for p in np.unique(packet)[:300]:
        assert np.ptp(first_sample[packet == p]) < 2e-3
    by_packet = read_waveform_las(out, agc_attribute=None, by_packet=True)
    assert by_packet.num_rows == packet.max() + 1
    te, tl = list_to_padded(by_packet.column("echo_time_ns"), dtype=np.float64)
    assert int(tl.sum()) == len(las.points)
    np.testing.assert_allclose(np.sort(te[np.arange(te.shape[1]) < tl[:, None]]),
                               np.sort(np.asarray(las.echo_time_ns, np.float64)), atol=1e-3)
    return las


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_point_format_9_keeps_each_echos_waveform(tmp_path, suffix):
    from waveforest.io.las import read_waveform_las

    out = tmp_path / f"echoes{suffix}"
    main(["decompose", str(RIEGL), "--out", str(out), "--nominal-range", "1000", "--point-format", "9",
          "--no-progress"])
    assert (tmp_path / "echoes.wdp").read_bytes() == RIEGL.with_suffix(".wdp").read_bytes()
    _check_waveforms_kept(read_waveform_las(RIEGL, agc_attribute=None), out)


def test_point_format_9_of_internal_waveforms_writes_them_beside(tmp_path):
    from waveforest.io.las import read_waveform_las, write_waveform_las

    src = read_waveform_las(RIEGL, agc_attribute=None).slice(0, 300)
    write_waveform_las(tmp_path / "in.las", src, version="1.4", bits=16, storage="internal", agc_attribute=None)
    main(["decompose", str(tmp_path / "in.las"), "--out", str(tmp_path / "e.las"), "--nominal-range", "1000",
          "--point-format", "9", "--no-progress"])
    assert (tmp_path / "e.wdp").is_file()
    _check_waveforms_kept(read_waveform_las(tmp_path / "in.las", agc_attribute=None), tmp_path / "e.las")


def test_point_format_9_never_overwrites_the_inputs_waveforms(tmp_path):
    import shutil

    for suffix in (".las", ".wdp"):
        shutil.copy(RIEGL.with_suffix(suffix), tmp_path / f"in{suffix}")
    before = (tmp_path / "in.wdp").read_bytes()
    with pytest.raises(SystemExit) as exc:
        main(["decompose", str(tmp_path / "in.las"), "--out", str(tmp_path / "in.laz"), "--point-format", "9",
              "--no-progress"])
    assert exc.value.code == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.las", "in.wdp"]
    assert (tmp_path / "in.wdp").read_bytes() == before


def test_decompose_refuses_a_wrong_output_name_and_writes_nothing(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["decompose", str(RIEGL), "--out", str(tmp_path / "echoes.txt"), "--no-progress"])
    assert exc.value.code == 2  # a bad option value: a usage error
    assert "'--out'" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_decompose_never_overwrites_its_input_las_or_wdp(tmp_path, monkeypatch, capsys):
    shutil.copy(RIEGL, tmp_path / "in.las")
    shutil.copy(RIEGL.with_suffix(".wdp"), tmp_path / "in.WDP")
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    (tmp_path / "wdp.las").symlink_to(tmp_path / "in.WDP")
    (tmp_path / "las.laz").symlink_to(tmp_path / "in.las")
    monkeypatch.chdir(tmp_path)
    for out in ("in.las", "./in.las", str(tmp_path / "in.las"), "wdp.las", "las.laz"):
        with pytest.raises(SystemExit) as exc:
            main(["decompose", "in.las", "--out", out, "--no-progress"])
        assert exc.value.code == 1, out
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "would overwrite the input" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.WDP", "in.las", "las.laz", "wdp.las"]
    assert all((tmp_path / name).read_bytes() == data for name, data in before.items())


def test_the_progress_bar_ends_full_when_the_header_undercounts_the_pulses(tmp_path, capsys):
    """The RIEGL header counts 2,365 first returns for 2,368 pulses."""
    main(["decompose", str(RIEGL), "--out", str(tmp_path / "e.las"), "--progress"])
    last = capsys.readouterr().err.replace("\n", "\r").rstrip("\r").rsplit("\r", 1)[-1]
    assert "100%" in last and "2.37k/2.37k" in last, last


def test_multi_echo_features_of_a_feature_table():
    """gd_* of ``feature_table`` against the echoes a synthetic pulse table was built from."""
    from fixtures.pulses import ECHO_FWHM_NS, synthetic_pulses

    from waveforest.constants import RANGE_PER_NS
    from waveforest.io.pulses import list_to_padded
    from waveforest.sensor.features import DECOMPOSITION_FEATURES, feature_table
    from waveforest.sensor.params import FeatureParams

    t = synthetic_pulses(400, seed=4, max_echoes=3)
    assert not set(DECOMPOSITION_FEATURES) & set(feature_table(t, {"synthetic": (10.0, 1.5, ECHO_FWHM_NS)}).columns)
    df = feature_table(t, {"synthetic": (10.0, 1.5, ECHO_FWHM_NS)}, FeatureParams(decomposition=True))
    assert set(DECOMPOSITION_FEATURES) <= set(df.columns)
    times, lens = list_to_padded(t.column("echo_time_ns"), dtype=np.float64)
    gaps = np.diff(times, axis=1)
    apart = np.all(np.nan_to_num(gaps, nan=np.inf) >= 2 * ECHO_FWHM_NS, axis=1)
    assert apart.sum() > 100
    n = df["gd_n"].to_numpy()
    assert np.mean(n[apart] == lens[apart]) >= 0.95
    ok = apart & (n == lens)
    span = (np.nanmax(times, axis=1) - times[:, 0]) * RANGE_PER_NS * np.abs(t.column("dir_z").to_numpy())
    np.testing.assert_allclose(df["gd_depth"].to_numpy()[ok], span[ok], atol=0.05)
    assert (df["gd_E"].to_numpy() > 0).all()
    np.testing.assert_array_equal(df["gd_later_A"].to_numpy()[(lens == 1) & ok], 0.0)


def test_merging_two_components_keeps_their_area_mean_and_variance():
    import waveforest.sensor.decompose as dec

    p = np.array([10.0, 20.0, 2.0, 6.0, 21.5, 3.0])
    area = p[0] * p[2] + p[3] * p[5]
    mean = (p[0] * p[2] * p[1] + p[3] * p[5] * p[4]) / area
    var = (p[0] * p[2] * (p[2] ** 2 + (p[1] - mean) ** 2) + p[3] * p[5] * (p[5] ** 2 + (p[4] - mean) ** 2)) / area
    assert dec._merge(p, 2, 1.0, 0.5, 10.0) == 1
    np.testing.assert_allclose([p[0] * p[2], p[1], p[2] ** 2], [area, mean, var], rtol=1e-12)


def test_the_exact_hessian_matches_finite_differences_of_the_cost():
    """The Newton step's Hessian, J^T W J minus the residual's second-derivative term, is the
    Hessian of half the weighted squared residual (Eq. F1)."""
    import waveforest.sensor.decompose as dec

    rng = np.random.default_rng(4)
    n, k = 60, 2
    ws = dec.scratch(n, 4)
    ws.y[:] = _waveforms([[(30.0, 25.0), (12.0, 31.0)]], n_samples=n, seed=2)[0] - 10.0
    ws.w[:] = 1.0
    ws.w[27] = 0.0  # a clipped sample weighs nothing
    p0 = np.array([25.0, 24.6, 2.6, 15.0, 31.8, 3.4]) + rng.normal(0.0, 0.05, 6)

    def half_cost(q):
        return 0.5 * dec._residual(ws.y, ws.w, q, k, 0, n, ws.ex2, ws.sup2, ws.r2)

    ws.p[:6] = p0
    dec._residual(ws.y, ws.w, ws.p, k, 0, n, ws.ex, ws.sup, ws.r)
    dec._normal_equations(ws.p, k, ws.w, ws.r, ws.ex, ws.sup, False, ws.jac, ws.grad, ws.hess, ws.second)
    h = np.tril(ws.hess[:6, :6])
    h = h + np.tril(h, -1).T
    for c in range(k):
        s = ws.second[c]
        block = np.array([[s[0], s[1], s[3]], [s[1], s[2], s[4]], [s[3], s[4], s[5]]])
        h[3 * c:3 * c + 3, 3 * c:3 * c + 3] -= block
    eps = 1e-4
    fd = np.empty((6, 6))
    for u in range(6):
        for v in range(6):
            q = [p0.copy() for _ in range(4)]
            q[0][u] += eps; q[0][v] += eps  # noqa: E702
            q[1][u] += eps; q[1][v] -= eps  # noqa: E702
            q[2][u] -= eps; q[2][v] += eps  # noqa: E702
            q[3][u] -= eps; q[3][v] -= eps  # noqa: E702
            fd[u, v] = (half_cost(q[0]) - half_cost(q[1]) - half_cost(q[2]) + half_cost(q[3])) / (4 * eps * eps)
    np.testing.assert_allclose(h, fd, rtol=2e-3, atol=2e-3 * np.abs(fd).max())
    # and the gradient is minus that of half the cost
    g = [(half_cost(p0 + eps * np.eye(6)[u]) - half_cost(p0 - eps * np.eye(6)[u])) / (2 * eps) for u in range(6)]
    np.testing.assert_allclose(ws.grad[:6], -np.array(g), rtol=1e-4, atol=1e-6 * np.abs(g).max())
