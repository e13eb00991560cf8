"""Scene container and its PLY files: round trip, validation, geometry."""

import numpy as np
import pytest

from waveforest.scene import Scene, SceneError, read_ply, write_ply


def _random_scene(n=50, seed=0):
    rng = np.random.default_rng(seed)
    tri = rng.normal(size=(n, 3, 3)).astype(np.float32)
    rho = rng.uniform(0, 0.5, n)
    tau = rng.uniform(0, 0.5, n)
    kind = rng.integers(0, 4, n)
    return Scene(tri, rho, tau, kind)


def test_ply_round_trip_is_exact(tmp_path):
    scene = _random_scene()
    path = write_ply(scene, tmp_path / "s.ply")
    back = read_ply(path)
    np.testing.assert_array_equal(back.triangles, scene.triangles)
    np.testing.assert_array_equal(back.rho, scene.rho)
    np.testing.assert_array_equal(back.tau, scene.tau)
    np.testing.assert_array_equal(back.kind, scene.kind)


def test_ply_file_is_the_one_plyfile_writes(tmp_path):
    """The packed writer and plyfile's element writer give the same bytes (any PLY reader)."""
    from plyfile import PlyData, PlyElement

    from waveforest.scene import PLY_COMMENT

    scene = _random_scene()
    n = len(scene)
    verts = np.empty(3 * n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    flat = scene.triangles.reshape(-1, 3)
    verts["x"], verts["y"], verts["z"] = flat.T
    faces = np.empty(n, dtype=[("vertex_indices", "<i4", (3,)), ("rho", "<f4"), ("tau", "<f4"), ("kind", "u1")])
    faces["vertex_indices"] = np.arange(3 * n).reshape(n, 3)
    faces["rho"], faces["tau"], faces["kind"] = scene.rho, scene.tau, scene.kind
    PlyData([PlyElement.describe(verts, "vertex"), PlyElement.describe(faces, "face")], text=False,
            byte_order="<", comments=[PLY_COMMENT]).write(str(tmp_path / "plyfile.ply"))
    ours = write_ply(scene, tmp_path / "ours.ply")
    assert ours.read_bytes() == (tmp_path / "plyfile.ply").read_bytes()


def test_ascii_ply_with_quads_is_fanned(tmp_path):
    text = """ply
format ascii 1.0
element vertex 4
property float x
property float y
property float z
element face 1
property list uchar int vertex_indices
property float rho
property float tau
property uchar kind
end_header
0 0 0
1 0 0
1 1 0
0 1 0
4 0 1 2 3 0.3 0 0
"""
    p = tmp_path / "quad.ply"
    p.write_text(text)
    s = read_ply(p)
    assert len(s) == 2
    assert s.areas.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(s.normals, [[0, 0, 1], [0, 0, 1]])
    assert np.all(s.rho == np.float32(0.3))


def test_ply_without_optical_properties_is_a_clear_error(tmp_path):
    p = tmp_path / "bare.ply"
    p.write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"
    )
    with pytest.raises(SceneError, match="rho, tau, kind"):
        read_ply(p)


def test_a_bare_ply_takes_a_default_material_and_its_polygons_fan(tmp_path):
    """A PLY without rho, tau, kind (any other tool's mesh) with ``default``: a triangle, a quad
    and a pentagon fanned from their first vertex, in file order, every face the default's."""
    p = tmp_path / "bare.ply"
    p.write_text(
        "ply\nformat ascii 1.0\nelement vertex 6\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 3\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0\n1 0 0\n1 1 0\n0 1 0\n0 2 1\n2 2 1\n3 0 1 2\n4 0 1 2 3\n5 1 2 5 4 3\n"
    )
    s = read_ply(p, default=(0.25, 0.5, 1))
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 2, 1], [2, 2, 1]], np.float32)
    want = v[[[0, 1, 2], [0, 1, 2], [0, 2, 3], [1, 2, 5], [1, 5, 4], [1, 4, 3]]]
    np.testing.assert_array_equal(s.triangles, want)
    assert np.all(np.broadcast_to(s.rho, 6) == np.float32(0.25)) and np.all(np.broadcast_to(s.kind, 6) == 1)
    assert np.all(np.broadcast_to(s.tau, 6) == np.float32(0.5))


def test_energy_conservation_is_enforced():
    tri = np.zeros((1, 3, 3), np.float32)
    with pytest.raises(SceneError, match="rho"):
        Scene(tri, 0.6, 0.5, 1)


def test_failed_write_leaves_existing_file(tmp_path):
    scene = _random_scene()
    path = write_ply(scene, tmp_path / "s.ply")
    before = path.read_bytes()

    class Boom(np.ndarray):  # fails after the header is written, as a full disk would
        def tobytes(self, *a, **k):
            raise RuntimeError("disk full")

    bad = _random_scene(seed=1)
    object.__setattr__(bad, "triangles", bad.triangles.view(Boom))
    with pytest.raises(RuntimeError):
        write_ply(bad, path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["s.ply"]


def test_concat_translate_bounds():
    a, b = _random_scene(10, 1), _random_scene(5, 2)
    c = Scene.concat([a, b.translated([10, 0, 0])])
    assert len(c) == 15
    assert c.bounds[1, 0] == pytest.approx(b.bounds[1, 0] + 10, abs=1e-5)
