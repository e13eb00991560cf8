"""Beams: validation, constructors and the Gaussian ray distribution across the beam."""

import math

import numpy as np
import pytest

from waveforest.mcrt import Beams, direction_from_angles
from waveforest.mcrt.kernels import BeamFrame, beam_keys, emit_rays

N = 40000
SD_RTOL = 0.02  # 2 % on an SD estimated from 40,000 rays (SE 0.35 %)


def _frame(beams, key=1):
    return BeamFrame(beams.origin, beams.direction, np.zeros(len(beams)), beam_keys(key, np.arange(len(beams))))


def test_direction_from_angles():
    d = direction_from_angles([0.0, 90.0, 30.0], [0.0, 90.0, 180.0])
    np.testing.assert_allclose(d[0], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(d[1], [1, 0, 0], atol=1e-12)  # azimuth 90 = east
    np.testing.assert_allclose(d[2], [0, -0.5, -np.sqrt(3) / 2], atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)


def test_toward_and_from_divergence():
    b = Beams.toward([1.0, 2.0, 0.0], 1200.0, 10.0, 45.0, divergence_mrad=0.15)
    np.testing.assert_allclose(b.origin[0] + 1200.0 * b.direction[0], [1, 2, 0], atol=1e-9)
    assert b.footprint_m[0] == pytest.approx(0.18)
    assert b.range_m[0] == 1200.0 and b.diverging.all()
    c = Beams.toward([0, 0, 0], [500.0, 1000.0], 0.0, 0.0, footprint_m=0.3)
    assert len(c) == 2 and not c.diverging.any()
    np.testing.assert_allclose(c.origin[:, 2], [500.0, 1000.0])
    assert len(c[1:]) == 1 and c[1].origin[0, 2] == 1000.0
    with pytest.raises(ValueError, match="exactly one"):
        Beams.toward([0, 0, 0], 1000.0)


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"origin": [0, 0, 1], "direction": [0, 0, -2], "footprint_m": 0.1}, "unit"),
        ({"origin": [0, 0, 1], "direction": [0, 0, -1], "footprint_m": -0.1}, "footprint_m"),
        ({"origin": [[0, 0, 1], [0, 0, 2]], "direction": [[0, 0, -1]] * 3, "footprint_m": 0.1}, "rows"),
        ({"origin": [0, 0, np.nan], "direction": [0, 0, -1], "footprint_m": 0.1}, "non-finite"),
        ({"origin": [0, 0, 1], "direction": [0, 0, -1], "footprint_m": 0.1, "range_m": -5.0}, "range_m"),
    ],
)
def test_beams_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        Beams(**kwargs)


def test_collimated_rays_follow_the_gaussian_irradiance():
    d = 0.8
    beams = Beams([0.0, 0.0, 100.0], [0.0, 0.0, -1.0], d)
    rays = emit_rays(_frame(beams), beams.footprint_m, beams.range_m, np.array([40.0]), N)
    xy = rays.origin[:, :2].astype(float)
    sd = d / (2 * math.sqrt(2))
    np.testing.assert_allclose(xy.std(axis=0), sd, rtol=SD_RTOL)
    # E(r) ~ exp(-(2r/d)^2): fraction of power within r = d/2 is 1 - 1/e
    inside = np.mean(np.hypot(xy[:, 0], xy[:, 1]) <= d / 2)
    assert inside == pytest.approx(1 - math.exp(-1), abs=4 * math.sqrt(0.23 / N))
    np.testing.assert_allclose(rays.origin[:, 2], 60.0, atol=1e-5)  # start plane 40 m from the sensor
    np.testing.assert_allclose(rays.path_m, 40.0)
    assert np.all(rays.direction == np.float32([0, 0, -1]))
    np.testing.assert_allclose(rays.power.sum(), 1.0)


def test_diverging_rays_have_the_footprint_at_the_range():
    rng_m, div = 1000.0, 0.5
    beams = Beams.from_divergence([0.0, 0.0, 0.0], direction_from_angles(20.0, 70.0), div, rng_m)
    axis = beams.direction[0]
    rays = emit_rays(_frame(beams), beams.footprint_m, beams.range_m, np.array([990.0]), N)
    d = rays.direction.astype(float)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # where each ray crosses the plane perpendicular to the axis at the range
    p = d * (rng_m / (d @ axis))[:, None] - rng_m * axis
    assert np.abs(p @ axis).max() < 1e-6
    r = np.linalg.norm(p, axis=1)
    sd = beams.footprint_m[0] / (2 * math.sqrt(2))
    assert np.sqrt(np.mean(r**2) / 2) == pytest.approx(sd, rel=SD_RTOL)
    # ray origins lie on the start plane, path = distance from the sensor
    np.testing.assert_allclose(rays.origin.astype(float) @ axis, 990.0, rtol=1e-6)
    np.testing.assert_allclose(rays.path_m, np.linalg.norm(rays.origin.astype(float), axis=1), rtol=1e-6)


def test_emission_depends_on_seed_and_beam_index_only():
    beams = Beams([[0.0, 0.0, 100.0]] * 2, [0.0, 0.0, -1.0], 0.5)
    a = emit_rays(_frame(beams, key=3), beams.footprint_m, beams.range_m, np.array([50.0, 50.0]), 1000)
    b = emit_rays(_frame(beams, key=3), beams.footprint_m, beams.range_m, np.array([50.0, 50.0]), 1000)
    c = emit_rays(_frame(beams, key=4), beams.footprint_m, beams.range_m, np.array([50.0, 50.0]), 1000)
    assert np.array_equal(a.origin, b.origin)
    assert not np.array_equal(a.origin, c.origin)
    assert not np.array_equal(a.origin[:1000], a.origin[1000:])  # two beams, two streams


def test_sincos_turn_is_within_an_ulp_of_the_exact_angle():
    """The emission's sin/cos of 2 pi u: exact at the quarter turns, and within 2.3e-16 of
    sin/cos of 2 pi u in extended precision everywhere (math.sin of the rounded 2 pi u is off by
    up to ~7e-16)."""
    from waveforest.mcrt.kernels import _sincos_turn

    for u, (s, c) in {0.0: (0, 1), 0.25: (1, 0), 0.5: (0, -1), 0.75: (-1, 0), 1.0: (0, 1)}.items():
        got = _sincos_turn(u)
        assert abs(got[0] - s) < 1e-16 and abs(got[1] - c) < 1e-16, u
    u = np.random.default_rng(3).random(2000)
    got = np.array([_sincos_turn(x) for x in u])
    if np.finfo(np.longdouble).precision < 18:
        pytest.skip("no extended precision for the reference angle")
    two_pi = 2 * np.longdouble("3.14159265358979323846264338327950288")
    angle = np.asarray(u, np.longdouble) * two_pi  # off by ~1e-18 at most
    assert np.abs(got[:, 0] - np.sin(angle)).max() < 2.3e-16
    assert np.abs(got[:, 1] - np.cos(angle)).max() < 2.3e-16
