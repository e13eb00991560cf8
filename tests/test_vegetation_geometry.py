"""Geometric building blocks: leaf outlines, leaf placement, prisms, placement, relief, coverage."""

import math

import numpy as np
import pytest
from reference_vegetation import coverage_reference, leaf_frames_reference, place_leaves_reference

from waveforest.scene import Scene
from waveforest.vegetation.gaps import coverage_kernel, nadir_coverage, nadir_gap_fraction
from waveforest.vegetation.ground import ground_plane, heightfield_triangles, relief_field
from waveforest.vegetation.leaves import (
    crossed_planes,
    leaf_frames,
    load_outline,
    place_leaves,
    triangulate,
)
from waveforest.vegetation.params import RES, ParameterFileError
from waveforest.vegetation.placement import thomas_positions, uniform_positions, wrap
from waveforest.vegetation.plant import isotropic
from waveforest.vegetation.wood import PRISM_CIRCUMRADIUS_PER_DIAMETER, prisms

OUTLINES = sorted(p.stem for p in (RES / "outlines").glob("*.csv"))


def _tri_area_2d(t):
    return 0.5 * ((t[:, 1, 0] - t[:, 0, 0]) * (t[:, 2, 1] - t[:, 0, 1])
                  - (t[:, 1, 1] - t[:, 0, 1]) * (t[:, 2, 0] - t[:, 0, 0]))


@pytest.mark.parametrize("name", OUTLINES)
def test_outline_triangulation_tiles_the_polygon(name):
    o = load_outline(name)
    a = _tri_area_2d(o.triangles)
    assert np.all(a > 0), "every triangle counter-clockwise, non-degenerate"
    assert a.sum() == pytest.approx(o.area, rel=1e-12)  # positive pieces summing to the area: a tiling
    assert o.n_triangles == len(o.vertices) - 2
    assert o.vertices[:, 0].min() == 0.0 and o.vertices[:, 0].max() == 1.0


def test_triangulation_of_a_concave_polygon():
    # an L shape of area 3: ear clipping must not cut across the notch
    poly = np.array([[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]], dtype=float)
    tri = poly[triangulate(poly)]
    a = _tri_area_2d(tri)
    assert np.all(a > 0) and a.sum() == pytest.approx(3.0)
    centroids = tri.mean(axis=1)
    assert not np.any((centroids[:, 0] > 1) & (centroids[:, 1] > 1))
    with pytest.raises(ValueError, match="counter-clockwise"):
        triangulate(poly[::-1])


def test_missing_outline_is_a_clear_error():
    with pytest.raises(ParameterFileError, match="no leaf outline named 'nope'"):
        load_outline("nope")


def test_placed_leaves_have_the_requested_area_normal_and_direction():
    rng = np.random.default_rng(0)
    o = load_outline("birch")
    n = 50
    normal = isotropic(n, rng)
    normal[normal[:, 2] < 0] *= -1
    toward = isotropic(n, rng)
    area = rng.uniform(5e-4, 3e-3, n)
    wf = 0.7
    length = o.length_for_area(area, wf)
    base = rng.normal(size=(n, 3))
    tri = place_leaves(o, base, normal, toward, length, wf)
    s = Scene(tri, 0.4, 0.4, 1)
    per_leaf = s.areas.reshape(n, o.n_triangles).sum(axis=1)
    np.testing.assert_allclose(per_leaf, area, rtol=1e-5)
    # float32 vertices of a few-cm leaf about 1 m from the origin: normals good to ~1e-4
    np.testing.assert_allclose(s.normals.reshape(n, -1, 3), np.repeat(normal[:, None], o.n_triangles, 1), atol=2e-4)
    # the tip (x = 1, y = 0) lies at base + length * (toward projected on the leaf plane)
    m, _ = leaf_frames(normal, toward)
    proj = toward - np.sum(toward * normal, 1, keepdims=True) * normal
    np.testing.assert_allclose(m, proj / np.linalg.norm(proj, axis=1, keepdims=True), atol=1e-12)


def test_leaf_frames_are_orthonormal_even_when_toward_is_parallel_to_the_normal():
    normal = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]])
    m, b = leaf_frames(normal, normal * 3.0)
    for v in (m, b):
        np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0)
    np.testing.assert_allclose(np.sum(m * normal, 1), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.cross(m, b), normal, atol=1e-12)


def test_leaf_frames_kernel_is_the_numpy_expressions_bit_for_bit():
    """The compiled frames equal the array expressions exactly (the plants, hence every table
    built on them, do not depend on which computes them), also where toward is parallel to
    the normal (both fallback axes) and for no leaves."""
    rng = np.random.default_rng(7)
    normal = isotropic(5000, rng)
    toward = isotropic(5000, rng) * rng.uniform(0.01, 10.0, (5000, 1))
    toward[::9] = normal[::9] * 3.0
    normal[::18] = [0.0, 0.0, 1.0]
    toward[::18] = [0.0, 0.0, 2.0]
    normal[9::18] = [0.95, 0.0, math.sqrt(1 - 0.95**2)]
    toward[9::18] = normal[9::18]
    for got, want in zip(leaf_frames(normal, toward), leaf_frames_reference(normal, toward)):
        np.testing.assert_array_equal(got, want)
    assert [a.shape for a in leaf_frames(np.empty((0, 3)), np.empty((0, 3)))] == [(0, 3), (0, 3)]


def test_place_kernel_agrees_with_numpy_reference():
    rng = np.random.default_rng(4)
    o = load_outline("raspberry_leaflet")
    n = 200
    normal = isotropic(n, rng)
    toward = isotropic(n, rng)
    base = rng.uniform(-3, 3, (n, 3))
    length = rng.uniform(0.01, 0.2, n)
    wf = rng.uniform(0.5, 2.0, n)
    fast = place_leaves(o, base, normal, toward, length, wf)
    m, b = leaf_frames(normal, toward)
    ref = place_leaves_reference(o.triangles, base, m, b, length, wf)
    np.testing.assert_allclose(fast, ref, atol=1e-6)
    assert place_leaves(o, np.empty((0, 3)), np.empty((0, 3)), np.empty((0, 3)), np.empty(0)).shape == (0, 3, 3)
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        place_leaves(o, base, normal[:5], toward, length)
    with pytest.raises(ValueError, match=">= 0"):
        place_leaves(o, base, normal, toward, -length)


def test_crossed_planes_are_perpendicular_and_share_the_axis():
    rng = np.random.default_rng(1)
    o = load_outline("rectangle")
    n = 20
    normal = np.abs(isotropic(n, rng)) * [1, 1, 1]
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    tri = crossed_planes(o, np.zeros((n, 3)), normal, isotropic(n, rng), 0.08, 0.5)
    s = Scene(tri, 0.4, 0.4, 1)
    n1 = s.normals[: n * 2].reshape(n, 2, 3)[:, 0]
    n2 = s.normals[n * 2:].reshape(n, 2, 3)[:, 0]
    np.testing.assert_allclose(np.sum(n1 * n2, axis=1), 0.0, atol=1e-5)
    np.testing.assert_allclose(n1, normal, atol=1e-5)
    assert np.all(n2[:, 2] >= -1e-6)
    assert s.areas.sum() == pytest.approx(2 * n * 0.08 * 0.08 * 0.5, rel=1e-5)


def test_prism_has_the_cylinder_lateral_area_and_outward_normals():
    rng = np.random.default_rng(2)
    n = 30
    p0 = rng.normal(size=(n, 3))
    p1 = p0 + rng.normal(size=(n, 3))
    d = rng.uniform(0.002, 0.05, n)
    tri = prisms(p0, p1, d, d)
    s = Scene(tri, 0.5, 0.0, 2)
    length = np.linalg.norm(p1 - p0, axis=1)
    # equal perimeter pi d -> lateral area pi d L (and mean caliper width d, Cauchy)
    np.testing.assert_allclose(s.areas.reshape(n, 6).sum(1), math.pi * d * length, rtol=1e-4)
    axis = (p1 - p0) / length[:, None]
    c = s.triangles.astype(float).mean(axis=1).reshape(n, 6, 3)
    rel = c - p0[:, None, :]
    radial = rel - np.sum(rel * axis[:, None], axis=2, keepdims=True) * axis[:, None]
    assert np.all(np.sum(radial * s.normals.reshape(n, 6, 3), axis=2) > 0)
    assert PRISM_CIRCUMRADIUS_PER_DIAMETER * 3 * math.sqrt(3) == pytest.approx(math.pi)
    with pytest.raises(ValueError, match="zero-length"):
        prisms(p0[:1], p0[:1], 0.01, 0.01)


def test_vertical_prism_projects_to_a_triangle_of_the_right_width():
    tri = prisms(np.array([[0.0, 0, 0]]), np.array([[0.0, 0, 1]]), 0.1, 0.1)
    xy = tri[:, :, :2].reshape(-1, 2)
    r = np.linalg.norm(xy, axis=1)
    np.testing.assert_allclose(r, PRISM_CIRCUMRADIUS_PER_DIAMETER * 0.1, rtol=1e-6)


def test_wrap_and_thomas_positions_stay_in_the_plot():
    x = np.array([-3.0, 2.999, 3.0, 4.5, -7.5])
    np.testing.assert_allclose(wrap(x), [-3.0, 2.999, -3.0, -1.5, -1.5])
    pts = thomas_positions(5000, np.random.default_rng(0), 0.2, 10)
    assert pts.min() >= -3 and pts.max() < 3
    uni = uniform_positions(5000, np.random.default_rng(0))

    def dispersion(p):  # variance / mean of counts in 0.5 m quadrats: 1 for a Poisson process
        counts = np.histogram2d(p[:, 0], p[:, 1], bins=12, range=[[-3, 3], [-3, 3]])[0]
        return counts.var() / counts.mean()

    assert 0.7 < dispersion(uni) < 1.4
    assert dispersion(pts) > 3.0
    with pytest.raises(ValueError):
        thomas_positions(10, np.random.default_rng(0), 0.0, 5)


def test_relief_field_has_the_exact_rms_and_the_gaussian_correlation_length():
    rng = np.random.default_rng(3)
    n, corr = 240, 0.3
    z = relief_field(rng, 0.05, corr, n)
    assert z.mean() == pytest.approx(0.0, abs=1e-12)
    assert z.std() == pytest.approx(0.05, rel=1e-12)
    # autocorrelation at lag r along x ~ exp(-r^2 / l^2) (periodic field)
    cell = 6.0 / n
    for lag in (5, 10):
        r = lag * cell
        c = np.mean(z * np.roll(z, lag, axis=1)) / z.var()
        assert c == pytest.approx(math.exp(-(r / corr) ** 2), abs=0.1)


def test_heightfield_triangles_cover_the_plot_and_face_up():
    z = np.zeros((12, 12))
    s = Scene(heightfield_triangles(z), 0.3, 0.0, 0)
    assert s.areas.sum() == pytest.approx(36.0, rel=1e-6)
    assert np.all(s.normals[:, 2] > 0.999)
    g = ground_plane(0.3)
    assert g.areas.sum() == pytest.approx(36.0) and np.all(g.normals[:, 2] == 1.0)


def test_coverage_kernel_agrees_with_brute_force_reference():
    rng = np.random.default_rng(8)
    tri = rng.uniform(-1, 1, (60, 3, 2)) * rng.uniform(0.05, 0.4, (60, 1, 1))
    tri += rng.uniform(-0.8, 0.8, (60, 1, 2))
    fast = coverage_kernel(tri, -1.0, -1.0, 0.02, 100, 100)
    ref = coverage_reference(tri, -1.0, -1.0, 0.02, 100, 100)
    np.testing.assert_array_equal(fast, ref)


def test_gap_fraction_of_a_square_leaf_is_analytic():
    # a horizontal 1 x 1 m leaf (2 triangles) over the 5 x 5 m region: gap 24/25
    sq = np.array([[[-0.5, -0.5, 1], [0.5, -0.5, 1], [0.5, 0.5, 1]],
                   [[-0.5, -0.5, 1], [0.5, 0.5, 1], [-0.5, 0.5, 1]]], dtype=np.float32)
    s = Scene.concat([Scene(sq, 0.4, 0.4, 1), ground_plane(0.3)])
    assert nadir_gap_fraction(s) == pytest.approx(24 / 25, abs=2e-3)
    assert nadir_gap_fraction(s, kinds=(2,)) == 1.0
    cov = nadir_coverage(s, cell_m=0.1, extent_m=1.0)
    assert cov.shape == (20, 20) and cov.sum() == 100
