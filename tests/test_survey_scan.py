"""Survey flight and scan geometry (no tracing): the three scan patterns, legs, a trajectory
with attitude; and the LAS 1.3 / internal-packet / LAZ outputs read back."""

from __future__ import annotations

import warnings

import laspy
import numpy as np
import pytest
import yaml
from fixtures.survey import fly as fly_survey
from fixtures.survey import tilted_plane, write_obj

from waveforest import config
from waveforest.settings import reference_system, sensor_settings
from waveforest.survey import SurveyError, load_survey
from waveforest.survey.scan import concat, fly, fly_blocks, leg_tracks, trajectory_table

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


def _survey(tmp_path, doc):
    (tmp_path / "SURVEY.yaml").write_text(yaml.safe_dump(doc))
    cfg = config.load(None)
    return load_survey(tmp_path / "SURVEY.yaml", sensor_settings(cfg), reference_system(cfg))


LEG = {"legs": [{"start": [0, 0], "end": [0, 62], "altitude_m": 1000.0, "speed_m_s": 62.0}]}


@pytest.mark.parametrize("pattern", ["oscillating", "polygon", "conic"])
def test_scan_patterns(tmp_path, pattern):
    sv = _survey(tmp_path, {"platform": LEG, "scanner": {"pattern": pattern, "scan_angle_deg": 10.0,
                                                         "pulse_rate_hz": 1000.0, "scan_frequency_hz": 5.0}})
    p = fly(sv, leg_tracks(sv))
    assert len(p) == 1001 and np.allclose(np.diff(p.gps_time), 1e-3)
    assert np.allclose(np.linalg.norm(p.direction, axis=1), 1.0)
    zenith = np.degrees(np.arccos(-p.direction[:, 2]))
    phase = np.mod(np.arange(len(p)) * 1e-3 * 5.0, 1.0)
    if pattern == "conic":  # constant zenith, azimuth turning with the phase (heading north: az 0 = +y)
        assert np.allclose(zenith, 10.0)
        az = np.mod(np.degrees(np.arctan2(p.direction[:, 0], p.direction[:, 1])), 360)
        assert np.allclose(np.mod(az - 360 * phase + 180, 360) - 180, 0, atol=1e-6)
    else:  # across track only (x), zig-zag or saw-tooth in the phase
        assert np.allclose(p.direction[:, 1], 0, atol=1e-12)
        across = np.degrees(np.arctan2(p.direction[:, 0], -p.direction[:, 2]))
        want = 10 * (1 - 4 * np.abs(phase - 0.5)) if pattern == "oscillating" else 10 * (2 * phase - 1)
        assert np.allclose(across, want, atol=1e-9)
        assert np.allclose(p.scan_angle_deg, want, atol=1e-9)
    assert np.allclose(p.origin[:, 2], 1000.0) and np.allclose(p.origin[:, 1], 62.0 * np.arange(len(p)) * 1e-3)
    blocks = concat(list(fly_blocks(sv, leg_tracks(sv), block=97)))  # blocks give the same pulses
    assert np.array_equal(blocks.direction, p.direction) and np.array_equal(blocks.gps_time, p.gps_time)


def test_legs_follow_each_other_and_a_trajectory_turns_the_beam(tmp_path):
    two = {"legs": [LEG["legs"][0], {"start": [100, 62], "end": [100, 0], "altitude_m": 900.0}], "turn_s": 10.0}
    sv = _survey(tmp_path, {"platform": two, "scanner": {"pulse_rate_hz": 100.0, "scan_angle_deg": 0.0}})
    tracks = leg_tracks(sv)
    assert tracks[1].gps_time[0] >= tracks[0].gps_time[-1] + 10.0
    assert tracks[1].attitude[0, 2] == pytest.approx(180.0)
    (tmp_path / "traj.csv").write_text("gps_time,x,y,z,roll_deg,pitch_deg,heading_deg\n"
                                       "0,0,0,500,5,0,90\n1,10,0,500,5,0,90\n")
    sv = _survey(tmp_path, {"platform": {"trajectory": "traj.csv"},
                            "scanner": {"pulse_rate_hz": 10.0, "scan_angle_deg": 0.0}})
    p = fly(sv, leg_tracks(sv))
    assert len(p) == 11 and np.allclose(p.origin[:, 0], np.arange(11))
    # heading east, roll 5 deg (right wing down): the body's down axis, the nadir beam, leans
    # 5 deg to the left of the track (north, +y)
    assert np.allclose(np.degrees(np.arccos(-p.direction[:, 2])), 5.0)
    assert np.all(p.direction[:, 1] > 0) and np.allclose(p.direction[:, 0], 0, atol=1e-12)
    (tmp_path / "traj.csv").write_text("gps_time,x,y,z\n0,0,0,500\n")
    with pytest.raises(SurveyError, match="missing column"):
        fly(sv, leg_tracks(sv))
    (tmp_path / "traj.csv").write_text("gps_time,x,y,z,roll_deg,pitch_deg,heading_deg\n"
                                       "0,0,0,500,0,0,0\n1,0,10,500,abc,0,0\n")
    with pytest.raises(SurveyError, match="column roll_deg, row 3: expected a finite number, got 'abc'"):
        leg_tracks(sv)


def test_a_trajectory_heading_through_north_turns_the_short_way(tmp_path):
    """359 -> 1 deg interpolates through 0 (not through 180), and the written heading stays in [0, 360)."""
    (tmp_path / "traj.csv").write_text("gps_time,x,y,z,roll_deg,pitch_deg,heading_deg\n"
                                       "0,0,0,500,10,0,359\n1,0,10,500,10,0,1\n")
    sv = _survey(tmp_path, {"platform": {"trajectory": "traj.csv"},
                            "scanner": {"pulse_rate_hz": 10.0, "scan_angle_deg": 0.0}})
    tracks = leg_tracks(sv)
    p = fly(sv, tracks)
    # roll 10 deg leans the nadir beam 10 deg to the left of the heading: azimuth heading - 90
    azimuth = np.degrees(np.arctan2(p.direction[:, 0], p.direction[:, 1]))
    assert np.allclose(np.mod(azimuth - (np.linspace(-1, 1, 11) - 90) + 180, 360) - 180, 0, atol=1e-9)
    assert np.allclose(np.degrees(np.arccos(-p.direction[:, 2])), 10.0)
    table = trajectory_table(tracks, 10.0)["heading_deg"].to_numpy()
    assert np.all((table >= 0) & (table < 360)) and np.allclose(np.mod(table + 1, 360), np.linspace(0, 2, 11))


def test_the_next_leg_starts_turn_s_after_the_end_of_the_last(tmp_path):
    """start_gps_time_s + duration + turn_s exactly (docs/survey.md: legs flown turn_s apart)."""
    two = {"legs": [{"start": [0, 0], "end": [0, 31], "speed_m_s": 62.0}, {"start": [5, 31], "end": [5, 0]}],
           "turn_s": 5.0, "start_gps_time_s": 1000.25}
    sv = _survey(tmp_path, {"platform": two, "scanner": {"pulse_rate_hz": 100.0, "scan_angle_deg": 0.0}})
    tracks = leg_tracks(sv)
    assert tracks[0].gps_time.tolist() == [1000.25, 1000.75]
    assert tracks[1].gps_time[0] == pytest.approx(1005.75, abs=1e-9)


def test_legs_without_a_turn_share_no_gps_time(tmp_path):
    """turn_s 0 and a whole number of pulse periods per leg: the next leg's first pulse would fall
    on the last one's GPS time (which the LAS writer refuses); it is not flown."""
    two = {"legs": [{"start": [0, 0], "end": [0, 62], "speed_m_s": 62.0},
                    {"start": [0, 62], "end": [0, 0], "speed_m_s": 62.0}], "turn_s": 0.0}
    sv = _survey(tmp_path, {"platform": two, "scanner": {"pulse_rate_hz": 100.0, "scan_angle_deg": 0.0}})
    p = fly(sv, leg_tracks(sv))
    assert len(np.unique(p.gps_time)) == len(p) == 201 and np.allclose(p.gps_time, np.arange(201) / 100.0)


def test_a_flight_past_a_gps_week_is_written_in_adjusted_standard_time(tmp_path):
    """start_gps_time_s beyond 604,800 s cannot be week time: the LAS file declares adjusted
    standard GPS time (global encoding bit 0); a flight within the week leaves the bit clear."""
    scene = {"ground": {"type": "plane", "z": 0.0, "rho": 0.3, "extent": [-100, -100, 100, 100]}}
    for start, bit in ((1000.0, 0), (3.2e8, 1)):
        out = f"out_{bit}"
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fly_survey(tmp_path, scene, {"pulse_rate_hz": 20.0, "scan_angle_deg": 0.0}, out=out,
                       quality={"rays_per_pulse": 64}, platform={"start_gps_time_s": start})
        las = laspy.read(tmp_path / out / "survey.las")
        assert int(las.header.global_encoding.value) & 1 == bit
        assert las.gps_time.min() >= start


@pytest.mark.parametrize("pattern", ["oscillating", "polygon", "conic"])
@pytest.mark.parametrize("hz", [10.0, 7.0])  # 50 pulses a sweep (one at each turn), 71.4 (none)
def test_scan_direction_and_edge_flags_follow_the_mirror(tmp_path, pattern, hz):
    """LAS 1.4 R15: the scan direction flag is 1 while the mirror travels left to right when the
    pulse leaves, the edge of flight line marks the last pulse of a sweep before it turns (or the
    facet changes), the pulse at the turn itself included; in the LAS points as in the pulses."""
    from waveforest.survey.scan import EDGE_OF_LINE, SCAN_POSITIVE

    scanner = {"pulse_rate_hz": 1000.0, "scan_frequency_hz": hz, "scan_angle_deg": 10.0, "pattern": pattern}
    long_leg = {"legs": [{"start": [0, 0], "end": [0, 62], "speed_m_s": 62.0}]}
    sv = _survey(tmp_path, {"platform": long_leg, "scanner": scanner})
    p = fly(sv, leg_tracks(sv))
    phase = np.mod(np.round((p.gps_time - p.gps_time[0]) * 1000.0) / 1000.0 * hz, 1.0)
    # the mirror's across-track motion at the phase: oscillating a (1 - 4 |p - 1/2|), conic
    # sin(a) sin(2 pi p), arriving at the pulse (at a turn: the sweep that ends there)
    left_to_right = {"oscillating": (phase > 0) & (phase <= 0.5 + 1e-9),
                     "conic": np.cos(2 * np.pi * (phase - 1e-9)) > 0, "polygon": np.ones(len(phase), bool)}[pattern]
    last = left_to_right[:-1] != left_to_right[1:] if pattern != "polygon" else phase[1:] < phase[:-1]
    positive = (p.scan_flags & SCAN_POSITIVE) > 0
    edge = (p.scan_flags & EDGE_OF_LINE) > 0
    assert np.array_equal(positive, left_to_right)
    assert np.array_equal(edge[:-1], last)
    if hz == 10.0 and pattern == "oscillating":  # the pulse at the turn is its sweep's outermost
        a = np.abs(p.scan_angle_deg)
        assert np.all(a[edge[:-1].nonzero()[0]] == pytest.approx(10.0))
    lines = {"oscillating": 2 * hz, "polygon": hz, "conic": 2 * hz}[pattern]  # sweeps in 1 s of flight
    assert abs(int(edge.sum()) - lines) <= 1
    if hz != 10.0:
        return
    scene = {"ground": {"type": "plane", "z": 0.0, "rho": 0.3, "extent": [-300, -300, 300, 300]}}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, table, _, _ = fly_survey(tmp_path, scene, scanner, length=6.2, quality={"rays_per_pulse": 16})
    las = laspy.read(tmp_path / "out" / "survey.las")
    flags = dict(zip(p.gps_time.round(9), p.scan_flags))
    want = np.array([flags[t] for t in np.asarray(las.gps_time).round(9)])
    assert len(want) >= 50 and edge[:len(want)].any()
    assert np.array_equal(np.asarray(las.scan_direction_flag), (want & SCAN_POSITIVE) > 0)
    assert np.array_equal(np.asarray(las.edge_of_flight_line), (want & EDGE_OF_LINE) > 0)
    assert np.all(np.asarray(las.point_source_id) == 1)  # leg 0: flight line 1
    assert np.all(np.diff(las.gps_time) >= 0)  # the swath's tiles merged in acquisition order


def test_the_written_heading_never_reads_360(tmp_path):
    """A heading interpolated to just below 360 deg (359 -> 1 between 100.0 and 100.2 s, at 100.1 s)
    is written 0.000000, not 360.000000 (docs/survey.md: heading 0 to 360 deg)."""
    (tmp_path / "traj.csv").write_text("gps_time,x,y,z,roll_deg,pitch_deg,heading_deg\n"
                                       "100.0,0,-10,900,0,0,359\n100.2,0,0,900,0,0,1\n")
    sv = _survey(tmp_path, {"platform": {"trajectory": "traj.csv"}, "scanner": {"pulse_rate_hz": 10.0}})
    text = trajectory_table(leg_tracks(sv), 10.0).to_csv(index=False, float_format="%.6f")
    heading = [line.split(",")[6] for line in text.splitlines()[1:]]
    assert heading == ["359.000000", "0.000000", "1.000000"]


def test_positive_pitch_raises_the_nose_and_leans_the_nadir_beam_forward(tmp_path):
    """Nose up (positive pitch, as the module docstring and HELIOS++ state) turns the body's
    down axis forward: heading north, pitch 5 deg puts the nadir beam 5 deg ahead (+y)."""
    (tmp_path / "traj.csv").write_text("gps_time,x,y,z,roll_deg,pitch_deg,heading_deg\n"
                                       "0,0,0,500,0,5,0\n1,0,10,500,0,5,0\n")
    sv = _survey(tmp_path, {"platform": {"trajectory": "traj.csv"},
                            "scanner": {"pulse_rate_hz": 10.0, "scan_angle_deg": 0.0}})
    d = fly(sv, leg_tracks(sv)).direction
    assert np.allclose(d[:, 0], 0.0, atol=1e-12) and np.allclose(d[:, 1], np.sin(np.radians(5.0)))
    assert np.allclose(d[:, 2], -np.cos(np.radians(5.0)))


def test_las13_internal_packets_and_laz(tmp_path):
    write_obj(tmp_path / "plane.obj", tilted_plane(20.0, 1.0))
    scene = {"objects": [{"file": "plane.obj", "materials": {"m": {"rho": 0.4}}}], "ground": {"type": "none"}}
    scanner = {"pulse_rate_hz": 40.0, "scan_angle_deg": 2.0, "scan_frequency_hz": 3.0}
    q = {"rays_per_pulse": 128, "max_order": 1}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r13, t13, _, _ = fly_survey(tmp_path, scene, scanner, altitude=300.0, quality=q, out="v13",
                                    output={"las_version": "1.3", "waveforms": "internal"})
        rz, tz, _, _ = fly_survey(tmp_path, scene, scanner, altitude=300.0, quality=q, out="vz",
                                  output={"laz": True})
    las = laspy.read(tmp_path / "v13" / "survey.las")
    assert (las.header.version.major, las.header.version.minor, las.header.point_format.id) == (1, 3, 4)
    assert not (tmp_path / "v13" / "survey.wdp").exists()
    assert t13.num_rows == r13["pulses_traced"] > 0
    laz = laspy.read(tmp_path / "vz" / "survey.laz")
    assert laz.header.point_format.id == 9 and len(laz.points) == rz["returns"]
    assert not (tmp_path / "vz" / "survey.las").exists() and (tmp_path / "vz" / "survey.wdp").exists()
    assert tz.num_rows == rz["pulses_traced"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fly_survey(tmp_path, scene, scanner, altitude=300.0, quality=q, out="v14")
    ref = laspy.read(tmp_path / "v14" / "survey.las")  # the same flight as LAS: the same points and records
    assert np.array_equal(laz.points.array, ref.points.array)
    assert [v.record_id for v in laz.header.vlrs if v.user_id != "laszip encoded"] == [
        v.record_id for v in ref.header.vlrs]
    assert (tmp_path / "vz" / "survey.wdp").read_bytes() == (tmp_path / "v14" / "survey.wdp").read_bytes()
