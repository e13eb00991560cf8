"""The ``waveforest vegetation`` command: PLY + PNG, seed from the config, clear errors."""

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from waveforest.cli import cli, main
from waveforest.scene import read_ply
from waveforest.stages.vegetation import run
from waveforest.vegetation import build_scene

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def test_writes_a_ply_that_reads_back_as_the_built_scene_and_a_png(tmp_path):
    out = tmp_path / "birch.ply"
    res = CliRunner().invoke(cli, ["vegetation", "--species", "birch", "--height", "3",
                                   "--seed", "7", "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "wrote" in res.output and "triangles" in res.output
    back = read_ply(out)
    ref = build_scene("birch", 3.0, 7)  # config defaults: ground_rho 0.30, lai_jitter 0.10
    np.testing.assert_array_equal(back.triangles, ref.triangles)
    np.testing.assert_array_equal(back.rho, ref.rho)
    np.testing.assert_array_equal(back.tau, ref.tau)
    np.testing.assert_array_equal(back.kind, ref.kind)
    png = out.with_suffix(".png")
    assert png.read_bytes()[:8] == PNG_MAGIC and png.stat().st_size > 10_000


def test_config_values_effects_and_options_reach_the_scene(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(yaml.safe_dump({"seed": 3, "vegetation": {"ground_rho": 0.2, "lai_jitter": 0.0}}))
    out = tmp_path / "b.ply"
    res = CliRunner().invoke(cli, ["vegetation", "--species", "birch", "--height", "3.0",
                                   "--config", str(cfg), "--out", str(out), "--no-png",
                                   "--effect", "understory=0.5", "--leaf-area-scale", "0.5"])
    assert res.exit_code == 0, res.output
    assert not out.with_suffix(".png").exists()
    back = read_ply(out)
    ref = build_scene("birch", 3.0, 3, ground_rho=0.2, lai_jitter=0.0, understory=0.5, leaf_area_scale=0.5)
    np.testing.assert_array_equal(back.triangles, ref.triangles)
    np.testing.assert_array_equal(back.rho, ref.rho)
    # half the allometric leaf area of a 3-m birch (3.251 m2, tests/test_vegetation_structure.py)
    # plus an understory of LAI 0.5 on the 36-m2 plot
    assert back.areas[back.kind == 1].sum() == pytest.approx(0.5 * 3.251 + 0.5 * 36, rel=1e-4)
    assert np.allclose(back.rho[back.kind == 0], 0.2)


def test_png_path_option_and_run_summary(tmp_path):
    s = run("sand_road", 0.0, 1, tmp_path / "a" / "road.ply", png=tmp_path / "pics" / "road.png", ground_rho=0.3,
            lai_jitter=0.1)
    assert s.ply.exists() and s.png.read_bytes()[:8] == PNG_MAGIC
    assert s.kind_counts[0] == s.n_triangles and s.lai == 0.0


@pytest.mark.parametrize("args,message", [
    (["--species", "oak", "--height", "3"], "species 'oak': unknown"),
    (["--species", "birch", "--height", "99"], "height 99.0 m for birch"),
    (["--species", "birch", "--height", "3", "--effect", "hotspot=1.3"], "acts in mcrt"),
    (["--species", "birch", "--height", "3", "--effect", "nonsense=1"], "unknown"),
])
def test_bad_input_exits_1_with_one_message_and_no_file(tmp_path, capsys, args, message):
    out = tmp_path / "x.ply"
    with pytest.raises(SystemExit) as exc:
        main(["vegetation", *args, "--out", str(out)])
    assert exc.value.code == 1
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_rasteriser_covers_a_triangle_and_keeps_the_nearest():
    """Sample centres inside a triangle are covered (its area in samples), and where two
    overlap the nearer one's colour is kept whatever the drawing order."""
    from waveforest.vegetation.render import rasterise

    big = [[0.0, 0.0], [40.0, 0.0], [0.0, 40.0]]  # area 800 samples
    small = [[5.0, 5.0], [15.0, 5.0], [5.0, 15.0]]
    red, blue = [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]
    for order in ((0, 1), (1, 0)):
        uv = np.array([big, small], float)[list(order)]
        depth = np.array([2.0, 1.0])[list(order)]  # the small one is nearer
        colour = np.array([red, blue])[list(order)]
        img = rasterise(uv, depth, colour, np.zeros(2), 1.0, 64, 64)
        assert abs(img[..., 3].sum() - 800) <= 40  # edge samples: within the perimeter's share
        assert img[63 - 8, 8, 2] == 1.0 and img[63 - 30, 5, 0] == 1.0  # row 0 is the top
        assert img[63 - 50, 50, 3] == 0.0
