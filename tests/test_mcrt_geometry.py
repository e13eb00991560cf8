"""Intersectors (Embree and NumPy), scene preparation, stuck rays and far sensors."""

import numba
import numpy as np
import pytest
from fixtures import scenes as syn

from waveforest.constants import C_M_PER_NS
from waveforest.mcrt import (
    Beams,
    DirectEmbreeIntersector,
    EmbreeIntersector,
    NumpyIntersector,
    prepare,
    trace,
    with_optics,
)
from waveforest.mcrt.backends import embree as rtc
from waveforest.mcrt.kernels import BeamFrame, _emit_kernel, emit_rays
from waveforest.mcrt.prepare import _box, _triangle_records
from waveforest.scene import Scene

T_RTOL = 1e-5  # float32 Embree vs float64 NumPy hit distance
AGREE_FRACTION = 0.999  # rays whose nearest triangle agrees (edge hits may differ by rounding)


def _random_triangles(rng, n, size=0.3):
    c = rng.uniform(-2, 2, (n, 1, 3))
    return (c + rng.normal(0, size, (n, 3, 3))).astype(np.float32)


def _random_rays(rng, m):
    o = rng.uniform(-3, 3, (m, 3)).astype(np.float32)
    d = rng.normal(size=(m, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return o, d.astype(np.float32)


EMBREE_KINDS = {
    "direct-high": lambda tri: DirectEmbreeIntersector(tri, "high"),
    "direct-medium": lambda tri: DirectEmbreeIntersector(tri, "medium"),
    "embreex": EmbreeIntersector,
}


def test_direct_embree_is_available():
    """The default backend calls Embree from Numba (else it silently falls back, slower)."""
    assert rtc.available(), rtc.unavailable_reason()
    assert prepare(syn.plane()).intersector.backend == "embree"
    assert isinstance(prepare(syn.plane()).intersector, DirectEmbreeIntersector)
    assert isinstance(prepare(syn.plane(), backend="embreex").intersector, EmbreeIntersector)


@pytest.mark.parametrize("kind", list(EMBREE_KINDS))
def test_embree_and_numpy_intersectors_agree_on_random_triangles(kind):
    rng = np.random.default_rng(1)
    tri = _random_triangles(rng, 300)
    o, d = _random_rays(rng, 3000)
    te, pe = EMBREE_KINDS[kind](tri).intersect(o, d)
    tn, pn = NumpyIntersector(tri).intersect(o, d)
    hit = pn >= 0
    assert 0.2 < hit.mean() < 0.95  # a real mix of hits and misses
    assert np.mean(pe == pn) >= AGREE_FRACTION
    same = (pe == pn) & hit
    np.testing.assert_allclose(te[same], tn[same], rtol=T_RTOL, atol=1e-6)
    assert np.all(np.isinf(te[pe < 0])) and np.all(np.isinf(tn[pn < 0]))


def _fan_leaves(rng, n_leaves, k=4):
    """Leaves of ``k`` fan triangles (centre, p_j, p_j+1) each, as vegetation outlines are cut,
    beside lone triangles: consecutive triangles share an edge within a leaf."""
    ang = np.linspace(0, np.pi, k + 1)
    out = []
    for _ in range(n_leaves):
        c = rng.uniform(-2, 2, 3)
        a, b = rng.normal(size=(2, 3)) * 0.3
        rim = c + np.cos(ang)[:, None] * a + np.sin(ang)[:, None] * b
        out += [np.stack([c, rim[j], rim[j + 1]]) for j in range(k)]
        if rng.random() < 0.3:
            out.append(_random_triangles(rng, 1)[0])
    return np.array(out, np.float32)


def test_quads_pair_the_triangles_that_share_an_edge_and_map_hits_back():
    """Embree gets consecutive triangles sharing an edge as one quad (faster builds): every
    triangle is one quad half with its own vertices, and a hit reports the triangle, as NumPy."""
    rng = np.random.default_rng(4)
    tri = _fan_leaves(rng, 150)
    quads, tri_of = rtc._pair_quads(tri)
    assert len(quads) < 0.6 * len(tri)  # most triangles paired
    halves = np.concatenate([tri_of[:, 0], tri_of[tri_of[:, 1] != tri_of[:, 0], 1]])
    assert np.array_equal(np.sort(halves), np.arange(len(tri)))  # each triangle once
    for q, (i, j) in zip(quads, tri_of):  # Embree's halves (v0, v1, v3) and (v2, v3, v1)
        assert {tuple(v) for v in q[[0, 1, 3]]} == {tuple(v) for v in tri[i]}
        if i != j:
            assert {tuple(v) for v in q[[2, 3, 1]]} == {tuple(v) for v in tri[j]}
    o, d = _random_rays(rng, 4000)
    for kind in ("direct-high", "direct-medium"):
        te, pe = EMBREE_KINDS[kind](tri).intersect(o, d)
        tn, pn = NumpyIntersector(tri).intersect(o, d)
        assert 0.1 < (pn >= 0).mean() < 0.95
        assert np.mean(pe == pn) >= AGREE_FRACTION
        same = (pe == pn) & (pn >= 0)
        np.testing.assert_allclose(te[same], tn[same], rtol=T_RTOL, atol=1e-6)


@pytest.mark.parametrize("backend", ["embree", "embreex", "numpy"])
def test_intersect_against_brute_force_geometry(backend):
    # single triangle at z = 1: rays from below straight up, inside / outside the triangle
    tri = np.array([[[0, 0, 1], [1, 0, 1], [0, 1, 1]]], np.float32)
    isect = prepare(Scene(tri, 0.5, 0.0, 1), backend=backend).intersector
    bounds_centre = 0.5 * (tri.reshape(-1, 3).min(0) + tri.reshape(-1, 3).max(0))
    o = np.array([[0.2, 0.2, 0.0], [0.8, 0.8, 0.0], [0.1, 0.1, 2.0]]) - bounds_centre
    d = np.array([[0, 0, 1.0], [0, 0, 1.0], [0, 0, 1.0]])
    t, p = isect.intersect(o.astype(np.float32), d.astype(np.float32))
    assert p.tolist() == [0, -1, -1]
    assert t[0] == pytest.approx(1.0, rel=1e-6)
    occ = isect.occluded(o.astype(np.float32), d.astype(np.float32), np.array([2.0, 2.0, 2.0], np.float32))
    assert occ.tolist() == [True, False, False]
    short = isect.occluded(o[:1].astype(np.float32), d[:1].astype(np.float32), np.array([0.5], np.float32))
    assert short.tolist() == [False]


@pytest.mark.parametrize("kind", list(EMBREE_KINDS))
def test_embree_and_numpy_occlusion_agree(kind):
    rng = np.random.default_rng(2)
    tri = _random_triangles(rng, 200)
    o, d = _random_rays(rng, 2000)
    tmax = rng.uniform(0.1, 5, 2000).astype(np.float32)
    oe = EMBREE_KINDS[kind](tri).occluded(o, d, tmax)
    on = NumpyIntersector(tri).occluded(o, d, tmax)
    assert 0.05 < on.mean() < 0.95
    assert np.mean(oe == on) >= AGREE_FRACTION


@pytest.mark.parametrize("kind", ["direct-high", "embreex"])
def test_embree_split_over_threads_is_identical(kind):
    rng = np.random.default_rng(3)
    tri = _random_triangles(rng, 500)
    o, d = _random_rays(rng, 20000)
    isect = EMBREE_KINDS[kind](tri)
    t1, p1 = isect.intersect(o, d, threads=1)
    t2, p2 = isect.intersect(o, d, threads=2)
    assert np.array_equal(p1, p2) and np.array_equal(t1, t2)
    tm = np.full(len(o), 1.0, np.float32)
    assert np.array_equal(isect.occluded(o, d, tm, threads=1), isect.occluded(o, d, tm, threads=2))


def _morton(q: np.ndarray) -> np.ndarray:
    """Z-order code of integer cell coordinates (n, 3), bit by bit (x lowest)."""
    key = np.zeros(len(q), np.int64)
    for b in range(10):
        for a in range(3):
            key |= ((q[:, a] >> b) & 1) << (3 * b + a)
    return key


@pytest.mark.parametrize("bits", [0, 1, 5])
def test_coherent_order_is_a_stable_z_order_permutation(bits):
    rng = np.random.default_rng(4)
    o = rng.uniform([-3, -3, 0], [3, 3, 1.2], (5000, 3)).astype(np.float32)
    order = rtc.coherent_order(o, bits)
    assert np.array_equal(np.sort(order), np.arange(len(o)))
    cells = 2 ** bits
    lo, hi = o.min(0), o.max(0)
    q = np.clip(((o - lo) * ((cells - 1) / (hi - lo))).astype(np.int64), 0, cells - 1)
    key = _morton(q)
    assert np.array_equal(order, np.argsort(key, kind="stable"))


def test_coherent_order_survives_degenerate_origins():
    o = np.zeros((7, 3), np.float32)  # one point: every ray in cell 0, order kept
    assert np.array_equal(rtc.coherent_order(o, 5), np.arange(7))
    o[2] = np.nan
    o[4, 0] = np.inf
    assert np.array_equal(np.sort(rtc.coherent_order(o, 5)), np.arange(7))


def test_direct_embree_results_do_not_depend_on_the_tracing_order(monkeypatch):
    rng = np.random.default_rng(5)
    isect = DirectEmbreeIntersector(_random_triangles(rng, 500))
    o, d = _random_rays(rng, 20000)
    tm = np.full(len(o), 1.0, np.float32)
    sorted_ = isect.intersect(o, d), isect.occluded(o, d, tm)
    monkeypatch.setattr(rtc, "CELL_BITS", 0)  # one cell: the rays' own order
    plain = isect.intersect(o, d), isect.occluded(o, d, tm)
    assert np.array_equal(sorted_[0][0], plain[0][0]) and np.array_equal(sorted_[0][1], plain[0][1])
    assert np.array_equal(sorted_[1], plain[1])
    monkeypatch.undo()
    as_given = isect.intersect(o, d, coherent=True)  # no Z-order sort at all
    assert np.array_equal(sorted_[0][0], as_given[0]) and np.array_equal(sorted_[0][1], as_given[1])
    assert (as_given[1] >= 0).sum() > 100  # hits exercised


def test_prepare_shifts_to_box_centre_and_keeps_properties():
    sc = syn.plane(4.0, z=2.0, rho=0.2, center=(1000.0, 2000.0))
    ps = prepare(sc)
    np.testing.assert_allclose(ps.shift, [1000.0, 2000.0, 2.0])
    np.testing.assert_allclose(ps.bounds, [[-2, -2, 0], [2, 2, 0]], atol=1e-3)
    np.testing.assert_allclose(ps.normals, [[0, 0, 1], [0, 0, 1]], atol=1e-6)
    assert np.all(ps.rho == np.float32(0.2)) and np.all(ps.tau == 0) and np.all(ps.kind == 0)
    assert prepare(ps) is ps
    with pytest.raises(ValueError, match="backend"):
        prepare(sc, backend="optix")
    with pytest.raises(ValueError, match="quality"):
        prepare(sc, quality="best")
    with pytest.raises(TypeError):
        prepare("scene.ply")



@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_prepared_boxes_are_the_vertices_extremes(dtype):
    """The one-pass box is NumPy's min and max over every vertex, and a prepared scene's
    shift and bounds are those of its vertices and of its internal float32 triangles."""
    tri = (_random_triangles(np.random.default_rng(3), 500) * 1000.0 + [6.7e6, 5.0e5, 90.0]).astype(dtype)
    v = tri.reshape(-1, 3)
    np.testing.assert_array_equal(_box(tri), np.stack([v.min(axis=0), v.max(axis=0)]).astype(np.float64))
    p = prepare(Scene(tri, np.full(500, 0.3, np.float32), np.zeros(500, np.float32), np.ones(500, np.uint8)))
    np.testing.assert_array_equal(p.shift, 0.5 * (v.min(axis=0).astype(float) + v.max(axis=0).astype(float)))
    internal = (tri.astype(np.float64) - p.shift).astype(np.float32).reshape(-1, 3)
    np.testing.assert_array_equal(p.bounds, np.stack([internal.min(axis=0), internal.max(axis=0)]).astype(np.float64))


def test_with_optics_traces_what_a_new_prepare_of_the_scene_traces():
    """New optics on the BVH of the same triangles: sigma bit for bit that of a scene prepared
    anew; other triangles are refused."""
    sheet = syn.sheet_over_ground(6.0, 0.3, rho=0.4, tau=0.4)
    brighter = Scene(sheet.triangles, np.where(sheet.kind == 1, 0.5, sheet.rho).astype(np.float32),
                     sheet.tau, sheet.kind)
    base = prepare(sheet)
    mine = with_optics(base, brighter)
    assert mine.intersector is base.intersector and mine.scene is brighter
    np.testing.assert_array_equal(mine.tri_data, prepare(brighter).tri_data)
    np.testing.assert_array_equal(base.rho, prepare(sheet).rho)  # the prepared scene is left alone
    beams = Beams.toward(np.zeros((3, 3)), 1000.0, [0.0, 5.0, 10.0], [0.0, 90.0, 200.0], divergence_mrad=0.15)
    kw = dict(n_rays=512, max_order=3, seed=4, sampler="sobol", roulette=0.5)
    np.testing.assert_array_equal(trace(mine, beams, **kw).sigma, trace(prepare(brighter), beams, **kw).sigma)
    with pytest.raises(ValueError, match="triangles"):
        with_optics(base, syn.plane(6.0))

def test_intersector_input_validation():
    with pytest.raises(ValueError, match="triangles"):
        EmbreeIntersector(np.zeros((0, 3, 3), np.float32))
    with pytest.raises(ValueError, match="triangles"):
        DirectEmbreeIntersector(np.zeros((0, 3, 3), np.float32))
    with pytest.raises(ValueError, match="quality"):
        DirectEmbreeIntersector(np.zeros((1, 3, 3), np.float32), "best")
    isect = NumpyIntersector(np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]]], np.float32))
    with pytest.raises(ValueError, match=r"\(m, 3\)"):
        isect.intersect(np.zeros((2, 2)), np.zeros((2, 2)))


@pytest.mark.parametrize("backend", ["embree", "embreex", "numpy"])
@pytest.mark.parametrize("zenith,rng_m", [(0.0, 1200.0), (15.0, 3000.0)])
def test_no_stuck_rays_on_a_single_sheet(backend, zenith, rng_m):
    """A ray leaving a surface must not re-hit it: a lone sheet scatters exactly once."""
    sheet = syn.plane(6.0, 0.5, rho=0.5, tau=0.5, kind=1)
    beams = Beams.toward([0.3, -0.2, 0.5], rng_m, zenith, 33.0, footprint_m=0.5)
    res = trace(prepare(sheet, backend=backend), beams, n_rays=4000, max_order=4, seed=1, sampler="random",
                roulette=0.0)
    assert res.first_hit_counts[0, 1] == 4000
    assert res.order_totals[0, 0] > 0
    assert np.all(res.order_totals[0, 1:] == 0)


@pytest.mark.parametrize("backend", ["embree", "embreex"])
def test_stuck_rays_in_a_closed_box_keep_scattering(backend):
    """Inside a closed cube every scattered ray must hit another wall (none escapes, none
    re-hits its own wall at t ~ 0): with rho = 1 the power is conserved order after order."""
    faces = []
    for axis in range(3):
        for sgn in (-1.0, 1.0):
            flat = syn.plane(2.0, 0.0, rho=1.0, kind=3).triangles.astype(np.float64)
            tri = np.empty_like(flat)
            tri[..., (axis + 1) % 3], tri[..., (axis + 2) % 3] = flat[..., 0], flat[..., 1]
            tri[..., axis] = sgn
            faces.append(Scene(tri.astype(np.float32), 1.0, 0.0, 3))
    box = Scene.concat(faces)
    ps = prepare(box, backend=backend)
    from waveforest.mcrt.kernels import BeamFrame, Rays, beam_keys, scatter

    m = 5000
    rng = np.random.default_rng(0)
    o = rng.uniform(-0.5, 0.5, (m, 3)).astype(np.float32)
    d = rng.normal(size=(m, 3))
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    rays = Rays(o, d, np.full(m, 1.0 / m), np.zeros(m), np.zeros(m, np.int32), np.arange(m, dtype=np.int32))
    frame = BeamFrame(np.array([[0.0, 0.0, 1000.0]]), np.array([[0.0, 0.0, -1.0]]), np.array([0.0]),
                      beam_keys(5, np.array([0])))
    face = None
    for order in range(1, 6):
        t, p = ps.intersector.intersect(rays.origin, rays.direction)
        assert np.all(p >= 0), "a ray escaped a closed box"
        if face is not None:  # the 6 faces are 2 triangles each; a wall cannot see itself
            assert np.all(p // 2 != face), "a ray re-hit the wall it left"
        face = p // 2
        out = scatter(order, False, rays, t, p, ps, frame, 10, 0.05, 5.0)
        assert np.all(out.alive)
        np.testing.assert_allclose(out.power.sum(), 1.0, rtol=1e-12)
        rays = Rays(out.origin.copy(), out.direction.copy(), out.power.copy(), out.path_m.copy(),
                    rays.beam, rays.ray)


@pytest.mark.parametrize("rng_m", [500.0, 1500.0, 3000.0])
def test_far_sensor_float_precision(rng_m):
    """sigma of a plane and its return time do not depend on how far the sensor is."""
    res = trace(syn.plane(6.0, 0.0, rho=0.3), Beams.toward([0, 0, 0], rng_m, 12.0, 200.0, footprint_m=0.05),
                n_rays=2000, max_order=2, seed=3, sampler="random", roulette=0.0)
    cos = np.cos(np.radians(12.0))
    assert res.total[0] == pytest.approx(0.3 * cos / np.pi, rel=1e-6)
    t = res.times_ns()[0] + 0.5 * res.bin_ns
    mean_t = np.sum(t * res.sigma[0]) / res.sigma[0].sum()
    assert mean_t == pytest.approx(2 * rng_m / C_M_PER_NS, abs=0.5 * res.bin_ns)


def test_read_only_scene_arrays_and_single_beams_do_not_compile_the_kernels_again():
    """A scene made of read-only arrays (a PLY buffer, an Arrow column) and a chunk of one beam
    (whose per-beam values are size-1 broadcasts) reach the kernels as writable arrays: Numba
    types a read-only array apart, so otherwise each would compile the kernel again."""
    if numba.config.DISABLE_JIT:
        pytest.skip("kernels run as Python")
    tri = np.array([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]] * 2, np.float32)
    counts = []
    for frozen, nb in ((False, 2), (True, 1)):
        arrays = [tri.copy(), np.full(2, 0.3, np.float32), np.full(2, 0.1, np.float32), np.ones(2, np.uint8)]
        for a in arrays:
            a.flags.writeable = not frozen
        prepare(Scene(*arrays))
        frame = BeamFrame(np.tile([0.0, 0.0, 100.0], (nb, 1)), np.tile([0.0, 0.0, -1.0], (nb, 1)), np.zeros(nb),
                          np.arange(nb, dtype=np.uint64))
        emit_rays(frame, 0.2, 100.0, 99.0, 8, "sobol")
        counts.append([len(k.signatures) for k in (_triangle_records, _emit_kernel)])
    assert counts[1] == counts[0]
