"""Two-level scenes (:func:`waveforest.mcrt.prepare_instances`): the same hits and sigma as
the flat scene of the placed triangles, and canopies assembled from leaf bricks that vary
between arrangements as much as new canopies do."""

import numpy as np
import pytest
from fixtures import scenes as syn

from waveforest.mcrt import Beams, prepare, prepare_instances, prepare_prototypes, trace
from waveforest.scene import Scene


def _placed(scene: Scene, rot, t) -> Scene:
    tri = np.einsum("ab,nvb->nva", rot, scene.triangles.astype(np.float64)) + t
    return Scene(tri.astype(np.float32), scene.rho, scene.tau, scene.kind)


def _turn(deg: float, axis=(0.3, -0.5, 0.8)) -> np.ndarray:
    a = np.asarray(axis) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    r = np.radians(deg)
    return np.eye(3) + np.sin(r) * k + (1 - np.cos(r)) * k @ k


@pytest.fixture(scope="module")
def arrangement():
    """Two leaf bricks and a ground, placed four times with arbitrary rotations far from
    the origin, and the flat scene of the same placed triangles."""
    parts = syn.leaf_bricks(2, 2.0, (0.0, 0.8), 1.0, 4e-3, seed=3) + [syn.plane(1.0, 0.0, 0.3)]
    which = np.array([0, 1, 0, 2])
    rot = np.stack([_turn(0), _turn(90, (0, 0, 1)), _turn(33), np.eye(3)])
    t = np.array([[500.0, 200.0, 1.0], [501.0, 200.0, 1.0], [500.5, 201.0, 1.2], [500.5, 200.5, 0.9]])
    flat = Scene.concat([_placed(parts[w], r, x) for w, r, x in zip(which, rot, t)])
    return prepare_prototypes(parts), which, rot, t, flat


def test_instances_hit_what_the_flat_scene_hits(arrangement):
    protos, which, rot, t, flat = arrangement
    inst = prepare_instances(protos, which, rot, t)
    ref = prepare(flat, quality="medium")
    assert len(inst) == len(flat)
    box, flat_box = inst.bounds + inst.shift, ref.bounds + ref.shift  # the box of turned boxes holds the triangles
    assert np.all(box[0] <= flat_box[0] + 1e-5) and np.all(box[1] >= flat_box[1] - 1e-5)
    assert np.all(box[1] - box[0] < 1.5 * (flat_box[1] - flat_box[0]))
    rng = np.random.default_rng(0)
    o = (rng.uniform(-0.8, 0.8, (20000, 3)) * [1.0, 1.0, 0.0] + [0.0, 0.0, 1.0]).astype(np.float32)
    d = rng.normal(size=(20000, 3))
    d[:, 2] = -np.abs(d[:, 2]) - 1.5
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    oi = o + (ref.shift - inst.shift).astype(np.float32)
    ti, pi = inst.intersector.intersect(oi, d)
    tf, pf = ref.intersector.intersect(o, d)
    hit = pf >= 0
    assert 0.3 < hit.mean() < 0.99
    assert np.mean(pi == pf) > 0.999  # same triangle (edge hits may differ by rounding)
    same = hit & (pi == pf)
    np.testing.assert_allclose(ti[same], tf[same], atol=1e-3)  # 1 mm: float32 transforms (bins are 7.5 mm)
    # turned normals (the flat ones carry the float32 rounding of coordinates near 500 m)
    np.testing.assert_allclose(inst.tri_data[pf[same]], ref.tri_data[pf[same]], atol=1e-3)
    blocked_i = inst.intersector.occluded(oi, d, np.full(len(o), 1.5, np.float32))
    blocked_f = ref.intersector.occluded(o, d, np.full(len(o), 1.5, np.float32))
    assert np.mean(blocked_i == blocked_f) > 0.999


def test_instances_trace_the_sigma_of_the_flat_scene(arrangement):
    protos, which, rot, t, flat = arrangement
    inst = prepare_instances(protos, which, rot, t)
    ref = prepare(flat, quality="medium")
    beams = Beams.toward(np.array([[500.3, 200.4, 1.0], [500.8, 200.6, 1.0]]), 1200.0, [0.0, 10.0], [0.0, 40.0],
                         divergence_mrad=2.0)
    a = trace(inst, beams, n_rays=4096, seed=4, sampler="sobol", roulette=0.5, by_order=True)
    b = trace(ref, beams, n_rays=4096, seed=4, sampler="sobol", roulette=0.5, by_order=True)
    def centroid_ns(r):  # mean two-way time of sigma (t0 differs: the box of turned boxes is larger)
        return (r.sigma * r.times_ns()).sum(axis=1) / r.sigma.sum(axis=1)

    np.testing.assert_allclose(centroid_ns(a), centroid_ns(b), atol=0.01)
    # same rays, same triangles: only float32 rounding of the hit points separates them
    np.testing.assert_allclose(a.order_totals[:, 0], b.order_totals[:, 0], rtol=1e-3)
    np.testing.assert_allclose(a.total, b.total, rtol=0.02)
    assert np.array_equal(a.first_hit_counts, b.first_hit_counts)


def test_prepare_instances_rejects_bad_input(arrangement):
    protos, which, rot, t, _ = arrangement
    with pytest.raises(ValueError, match="orthonormal"):
        prepare_instances(protos, which, rot * 1.1, t)
    with pytest.raises(ValueError, match="orthonormal"):
        prepare_instances(protos, which, rot @ np.diag([1.0, 1.0, -1.0]), t)  # a mirror
    with pytest.raises(ValueError, match="part index"):
        prepare_instances(protos, which + 5, rot, t)
    with pytest.raises(ValueError, match="instances"):
        prepare_instances(protos, which, rot, t[:2])
    with pytest.raises(TypeError):
        prepare_instances([flat for flat in protos.scenes], which, rot, t)


def test_brick_canopies_vary_between_arrangements_as_new_canopies_do():
    """The paper's rule is a new canopy per pulse. Arrangements of a 32-brick library (3 x 3
    bricks, each turned by a random multiple of 90 deg) must give pulses whose total and
    first-order sigma have the mean and the between-canopy spread of new random_leaves
    canopies (Monte Carlo noise is ~5 % of that spread here)."""
    n, lai, z, side, leaf, library = 40, 2.0, (0.0, 0.8), 1.0, 4e-3, 32
    rng = np.random.default_rng(100)
    aim = np.column_stack([rng.uniform(-0.5, 0.5, (n, 2)), np.zeros(n)])
    beams = Beams.toward(aim, 1200.0, 0.0, 0.0, divergence_mrad=0.15)
    kw = dict(n_rays=1024, sampler="sobol", roulette=0.5, max_order=5)
    protos = prepare_prototypes(syn.leaf_bricks(library, lai, z, side, leaf, seed=500)
                                + [syn.plane(3 * side, 0.0, 0.3)])
    assembled, fresh = np.empty((n, 2)), np.empty((n, 2))
    for i in range(n):
        inst = prepare_instances(protos, *syn.brick_canopy(library, 3, side, rng))
        r = trace(inst, beams[i:i + 1], seed=i, **kw)
        assembled[i] = r.total[0], r.order_totals[0, 0]
        r = trace(syn.random_leaves(lai, z, 3 * side, leaf, seed=20000 + i), beams[i:i + 1], seed=i, **kw)
        fresh[i] = r.total[0], r.order_totals[0, 0]
    se = np.sqrt(assembled.var(axis=0, ddof=1) / n + fresh.var(axis=0, ddof=1) / n)
    assert np.all(np.abs(assembled.mean(axis=0) - fresh.mean(axis=0)) < 3 * se)
    ratio = assembled.var(axis=0, ddof=1) / fresh.var(axis=0, ddof=1)
    assert np.all((ratio > 0.5) & (ratio < 2.0)), ratio  # F(39, 39): 95 % of ratios in [0.53, 1.89]
    assert np.all(fresh.std(axis=0) > 0.03 * fresh.mean(axis=0))  # a real spread between canopies
