"""A real file nobody here wrote: RIEGL LAS 1.4 point format 9, 16-bit samples in a .wdp.

See tests/data/real/README.md. Every waveform sample, echo and geometry value of our
reader is compared with an independent struct-based reading (tests/reference_io.py).
"""

import numpy as np
import pytest
from reference_io import RIEGL, reference_points, reference_pulses

from waveforest.constants import RANGE_PER_NS
from waveforest.io.las import WaveformPulseReader, open_waveform_las, read_waveform_las
from waveforest.io.las.format import LasWaveformWarning

QUANT_M = 0.001
"""Coordinate scale of the RIEGL file, m."""
ANCHOR_TOL_M = 2.0 * np.sqrt(3.0) * QUANT_M
"""Two returns' anchors differ by at most two quantisation errors of a 3-D point."""


@pytest.fixture(scope="module")
def table():
    with pytest.warns(LasWaveformWarning, match="user_data"):
        return read_waveform_las(RIEGL)


@pytest.fixture(scope="module")
def reference():
    return reference_pulses(RIEGL)


def test_header_facts():
    las = open_waveform_las(RIEGL)
    assert (las.version, las.point_format, las.record_length, las.n_points) == ("1.4", 9, 63, 2535)
    assert las.waveform.storage == "external" and las.waveform.header_ok
    assert las.waveform.path.name == "riegl_fwf.wdp" and las.waveform.size == 292_740
    assert len(las.descriptors) == 100
    assert sum(d.empty for d in las.descriptors.values()) == 98
    d1, d2 = las.descriptors[1], las.descriptors[2]
    assert (d1.bits, d1.compression, d1.n_samples, d1.spacing_ps, d1.gain, d1.offset) == (16, 0, 60, 1000, 1.0, 0.0)
    assert (d2.n_samples, d2.spacing_ps) == (120, 1000)
    assert set(las.extra_dimension_names) == {"Amplitude", "Pulse width"}


def test_pulse_count_and_grouping(table):
    # README: 2,368 distinct GPS times; 7 pulses have their returns in two packets
    assert table.num_rows == 2368
    assert np.all(np.diff(table["gps_time"].to_numpy()) > 0)
    assert table["pulse_id"].to_numpy().tolist() == list(range(2368))
    assert int(table["n_echoes"].to_numpy().sum()) == 2535
    reader = WaveformPulseReader(RIEGL)
    with pytest.warns(LasWaveformWarning):
        list(reader)
    assert reader.stats.n_split_pulses == 7 and reader.stats.n_pulses == 2368


def test_by_packet_gives_each_packet_its_own_row():
    """by_packet (decompose's reading): one row per (pulse, packet) of the independent reading,
    with that packet's 16-bit samples and its returns at their own location in it."""
    back = read_waveform_las(RIEGL, agc_attribute=None, by_packet=True)
    groups = {}
    for p in reference_points(RIEGL):
        groups.setdefault((p["gps"], p["off"]), []).append(p)
    assert back.num_rows == len(groups) == 2375
    pid = back["pulse_id"].to_numpy()
    assert len(np.unique(pid)) == 2368 and np.all(np.diff(pid) >= 0)
    assert int(back["n_echoes"].to_numpy().sum()) == 2535
    wdp = RIEGL.with_suffix(".wdp").read_bytes()
    anchor = np.column_stack([back[f"anchor_{a}"].to_numpy() for a in "xyz"])
    direction = np.column_stack([back[f"dir_{a}"].to_numpy() for a in "xyz"])
    rows = zip(back["gps_time"].to_numpy(), back["samples"].to_pylist(), back["echo_time_ns"].to_pylist(),
               back["echo_x"].to_pylist())
    for i, (gps, samples, times, ex) in enumerate(rows):
        if i % 50 and pid[i] not in pid[np.flatnonzero(np.diff(pid) == 0)]:
            continue  # every 50th row and every pulse with several packets
        pts = next(v for (g, _), v in groups.items() if g == gps and v[0]["x"] in ex)
        raw = wdp[pts[0]["off"]:pts[0]["off"] + pts[0]["size"]]
        assert samples == np.frombuffer(raw, "<u2").tolist()
        assert sorted(ex) == sorted(p["x"] for p in pts)
        for p, t in zip(sorted(pts, key=lambda q: q["loc"]), sorted(times)):  # each return on its packet's line
            assert t == pytest.approx(p["loc"] / 1000.0)  # (air against vacuum c/2: as the test below)
            at = anchor[i] + direction[i] * t * RANGE_PER_NS
            assert np.linalg.norm(at - [p["x"], p["y"], p["z"]]) < ANCHOR_TOL_M + 3e-4 * RANGE_PER_NS * t


def test_every_sample_exact(table, reference):
    assert len(reference) == table.num_rows
    samples = table["samples"].to_pylist()
    for mine, ref in zip(samples, reference):
        assert mine == ref["samples"]  # float32 holds 16-bit values exactly
    flat = np.concatenate([np.asarray(s) for s in samples])
    assert flat.min() == 0 and flat.max() == 248  # README: sample values range from 0 to 248
    lengths = np.array([len(s) for s in samples])
    assert set(lengths) == {60, 120}


def test_echoes_times_and_geometry_match_reference(table, reference):
    np.testing.assert_array_equal(table["gps_time"].to_numpy(), [p["gps"] for p in reference])
    np.testing.assert_array_equal(table["sampling_ns"].to_numpy(), [p["sampling_ns"] for p in reference])
    anchor = np.stack([table[f"anchor_{c}"].to_numpy() for c in "xyz"], axis=1)
    direction = np.stack([table[f"dir_{c}"].to_numpy() for c in "xyz"], axis=1)
    np.testing.assert_allclose(anchor, [p["anchor"] for p in reference], rtol=0, atol=1e-9)
    np.testing.assert_allclose(direction, [p["dir"] for p in reference], rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(direction, axis=1), 1.0, rtol=0, atol=1e-12)
    assert np.all(direction[:, 2] < 0)  # sensor -> target points down
    for col, k in (("echo_x", 0), ("echo_y", 1), ("echo_z", 2), ("echo_time_ns", 3), ("echo_intensity", 4)):
        mine = np.concatenate(table[col].to_numpy(zero_copy_only=False))
        ref = np.array([e[k] for p in reference for e in p["echoes"]])
        np.testing.assert_allclose(mine, ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(table["scan_angle_deg"].to_numpy(), [p["scan_deg"] for p in reference], atol=1e-9)
    assert np.all(np.isnan(table["agc"].to_numpy()))  # user_data is 0: no AGC, not faked
    assert np.all(np.isnan(table["range_m"].to_numpy()))


def test_las_relation_reproduces_each_return(table):
    """anchor + dir * t * RANGE_PER_NS gives back each return in the chosen packet.

    The RIEGL |(x(t), y(t), z(t))| is c/2 in air, ours RANGE_PER_NS is c/2 in vacuum: the
    0.03 % difference over the echo time is allowed for besides the 1 mm quantisation.
    """
    pts = reference_points(RIEGL)
    speed = np.median([np.sqrt(p["xt"] ** 2 + p["yt"] ** 2 + p["zt"] ** 2) for p in pts]) * 1000.0  # m/ns
    anchor = np.stack([table[f"anchor_{c}"].to_numpy() for c in "xyz"], axis=1)
    direction = np.stack([table[f"dir_{c}"].to_numpy() for c in "xyz"], axis=1)
    n_echo = table["n_echoes"].to_numpy()
    t = np.concatenate(table["echo_time_ns"].to_numpy(zero_copy_only=False))
    xyz = np.stack([np.concatenate(table[f"echo_{c}"].to_numpy(zero_copy_only=False)) for c in "xyz"], axis=1)
    p = np.repeat(np.arange(table.num_rows), n_echo)
    in_record = t < table["sampling_ns"].to_numpy()[p] * np.array([len(s) for s in table["samples"].to_pylist()])[p]
    model = anchor[p] + direction[p] * (t * speed)[:, None]
    miss = np.linalg.norm(model - xyz, axis=1)[in_record]
    assert miss.max() <= ANCHOR_TOL_M
    # and with our RANGE_PER_NS, up to the air/vacuum scale difference
    model_vac = anchor[p] + direction[p] * (t * RANGE_PER_NS)[:, None]
    miss_vac = np.linalg.norm(model_vac - xyz, axis=1)[in_record]
    assert np.all(miss_vac <= ANCHOR_TOL_M + abs(RANGE_PER_NS - speed) * t[in_record] + 1e-9)


def test_split_pulses_keep_both_returns(table):
    """The 7 pulses with returns in two packets: one row, both echoes, times from geometry."""
    n_echo = table["n_echoes"].to_numpy()
    times = table["echo_time_ns"].to_pylist()
    gps = table["gps_time"].to_numpy()
    # README example: GPS 400992.52564537 has returns at z 361.547 (r1) and 350.879 (r2)
    row = int(np.flatnonzero(np.isclose(gps, 400992.52564537, rtol=0, atol=1e-8))[0])
    assert n_echo[row] == 2
    z = table["echo_z"].to_pylist()[row]
    np.testing.assert_allclose(z, [361.547, 350.879], atol=1e-6)
    t1, t2 = times[row]
    assert t1 == pytest.approx(16.049789, abs=1e-5)  # L / 1000 of the first return's own packet
    # second return, in another packet: its distance behind the first along the beam
    d = np.linalg.norm(np.array([548348.523, 5389941.724, 350.879]) - np.array([548349.853, 5389941.43, 361.547]))
    assert t2 - t1 == pytest.approx(d / RANGE_PER_NS, abs=0.02)
