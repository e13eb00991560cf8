"""`waveforest survey`: bad input (one line, exit 1, no output), outputs that read back
(laspy, `info`, the pulse reader), resuming from completed tiles, parts, the same seed
giving the same files, plants as instances of prototypes."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import laspy
import numpy as np
import pandas as pd
import pytest
import yaml
from fixtures.cli import run_cli
from fixtures.survey import fly, tilted_plane, write_obj

from waveforest import config
from waveforest.cli import main
from waveforest.settings import mcrt_setup, reference_system, sensor_settings
from waveforest.survey import SurveyError, load_scene, load_survey, survey_mcrt
from waveforest.survey.engine import plan, run_key, tile_side
from waveforest.survey.run import cache_folder
from waveforest.survey.spec import AGC_LAW

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")

PLANE = {"objects": [{"file": "plane.obj", "materials": {"m": {"rho": 0.4}}}], "ground": {"type": "none"}}
SURVEY = {"platform": {"legs": [{"start": [0, -3], "end": [0, 3], "altitude_m": 300.0}]},
          "scanner": {"pulse_rate_hz": 40.0, "scan_angle_deg": 2.0, "scan_frequency_hz": 3.0},
          "quality": {"rays_per_pulse": 256, "max_order": 2, "tile_m": 2.0}}


def _files(tmp_path, scene=None, survey=None):
    write_obj(tmp_path / "plane.obj", tilted_plane(20.0, 1.0))
    (tmp_path / "SCENE.yaml").write_text(yaml.safe_dump(PLANE if scene is None else scene))
    (tmp_path / "SURVEY.yaml").write_text(yaml.safe_dump(SURVEY if survey is None else survey))
    return tmp_path / "SCENE.yaml", tmp_path / "SURVEY.yaml"


def _run(argv, capsys):
    """``main(argv)``: its exit code (0 when it returns) and its non-empty stderr lines."""
    code, _, err = run_cli(argv, capsys)
    return code, [ln for ln in err.splitlines() if ln.strip()]


def _fails(tmp_path, capsys, scene=None, survey=None, expect=""):
    sc, sv = _files(tmp_path, scene, survey)
    out = tmp_path / "out"
    code, lines = _run(["survey", sc, sv, "--out", out, "--no-progress"], capsys)
    assert code == 1, lines
    assert len(lines) == 1 and lines[0].startswith("waveforest: error: "), lines
    assert expect in lines[0], lines[0]
    assert not out.exists()
    assert not any(p.name.startswith(".out.") for p in tmp_path.iterdir())
    return lines[0]


def test_unknown_keys_in_either_file(tmp_path, capsys):
    line = _fails(tmp_path, capsys, scene={**PLANE, "grund": {}}, expect="SCENE.yaml: grund: unknown key")
    assert "expected one of objects, plants, ground" in line
    survey = {**SURVEY, "scanner": {**SURVEY["scanner"], "pulse_rate": 5}}
    _fails(tmp_path, capsys, survey=survey, expect="SURVEY.yaml: scanner/pulse_rate: unknown key")
    survey = {**SURVEY, "platform": {"legs": [{"start": [0, 0], "end": [0, 1], "speed": 3}]}}
    _fails(tmp_path, capsys, survey=survey, expect="platform/legs/0/speed: unknown key")
    survey = {**SURVEY, "quality": {"tolerance": 0.2, "rays_per_pulse": 512}}  # which one would win?
    _fails(tmp_path, capsys, survey=survey, expect="quality: expected tolerance (an adaptive budget) or rays_per_pulse")


def test_a_mesh_that_cannot_be_read(tmp_path, capsys):
    scene = {"objects": [{"file": "nowhere.obj"}]}
    _fails(tmp_path, capsys, scene=scene, expect="objects/0: ")
    (tmp_path / "junk.ply").write_bytes(b"\x00garbage" * 10)
    _fails(tmp_path, capsys, scene={"objects": [{"file": "junk.ply"}]}, expect="junk.ply")


def test_non_finite_vertices(tmp_path, capsys):
    (tmp_path / "nan.obj").write_text("usemtl m\nv 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n")
    scene = {"objects": [{"file": "nan.obj", "materials": {"m": {"rho": 0.4}}}]}
    _fails(tmp_path, capsys, scene=scene, expect="non-finite vertex")


def test_an_empty_scene(tmp_path, capsys):
    _fails(tmp_path, capsys, scene={"ground": {"type": "none"}}, expect="the scene is empty")


def test_a_material_without_properties(tmp_path, capsys):
    scene = {"objects": [{"file": "plane.obj"}], "ground": {"type": "none"}}
    _fails(tmp_path, capsys, scene=scene, expect="material 'm' has no optical properties")


def test_a_leg_that_sees_no_scene(tmp_path, capsys):
    survey = {**SURVEY, "platform": {"legs": [SURVEY["platform"]["legs"][0],
                                              {"start": [500, 0], "end": [500, 10], "altitude_m": 300.0}]}}
    _fails(tmp_path, capsys, survey=survey, expect="platform/legs/1: the leg sees no part of the scene")


def test_a_sensor_inside_the_scene(tmp_path, capsys):
    """A leg flown below the top of the scene it looks at (the tilted plane reaches ~0.17 m)."""
    survey = {**SURVEY, "platform": {"legs": [SURVEY["platform"]["legs"][0],
                                              {"start": [0, -3], "end": [0, 3], "altitude_m": 0.05}]}}
    _fails(tmp_path, capsys, survey=survey, expect="platform/legs/1: the sensor flies inside the scene")


def test_scanner_and_output_values_that_cannot_work_fail_before_any_tracing(tmp_path, capsys):
    """A record too short to hold an echo past its pre-trigger (its pulses had no return and were
    left out of the LAS, unsaid), a sampling interval LAS cannot store (the merge failed after
    all tracing), a CRS that is no WKT or gives degrees for the scene's metres, and a start time
    a trajectory would ignore: one line naming the key."""
    short = {**SURVEY, "scanner": {**SURVEY["scanner"], "record_ns": 26.0}}
    _fails(tmp_path, capsys, survey=short, expect="scanner/record_ns: 26 ns cannot hold an echo")
    odd = {**SURVEY, "scanner": {**SURVEY["scanner"], "sampling_ns": 0.3333}}
    _fails(tmp_path, capsys, survey=odd, expect="scanner/sampling_ns: 0.3333 ns is not a whole number of picoseconds")
    for wkt, why in (("EPSG:32635", "expected OGC WKT"), ('PROJCS["x",GEOGCS["y"]', "brackets and quotes close"),
                     ('GEOGCS["WGS 84",DATUM["WGS_1984"],UNIT["degree",0.0174532925199433]]', "degrees")):
        line = _fails(tmp_path, capsys, survey={**SURVEY, "output": {"crs_wkt": wkt}}, expect="output/crs_wkt: ")
        assert why in line, line
    (tmp_path / "traj.csv").write_text("gps_time,x,y,z,roll_deg,pitch_deg,heading_deg\n0,0,-3,300,0,0,0\n1,0,3,300,0,0,0\n")
    timed = {**SURVEY, "platform": {"trajectory": "traj.csv", "start_gps_time_s": 5000.0}}
    _fails(tmp_path, capsys, survey=timed, expect="platform/start_gps_time_s: expected null with a trajectory")


def test_pulses_without_a_return_are_counted(tmp_path, capsys):
    """Beams between two plates cross the scene's box but return nothing, so they have no point
    in the LAS: the summary and the command's line say how many."""
    write_obj(tmp_path / "plate.obj", tilted_plane(2.0, 1.0))
    plate = {"file": "plate.obj", "materials": {"m": {"rho": 0.4}}}
    scene = {"objects": [{**plate, "translate": [-6.0, 0.0, 0.0]}, {**plate, "translate": [6.0, 0.0, 0.0]}],
             "ground": {"type": "none"}}
    sc, sv = _files(tmp_path, scene, {**SURVEY, "scanner": {**SURVEY["scanner"], "pulse_rate_hz": 200.0}})
    out = tmp_path / "out"
    code, said, _ = run_cli(["survey", sc, sv, "--out", out, "--no-progress"], capsys)
    assert code == 0
    summary = json.loads((out / "summary.json").read_text())
    las = laspy.read(out / "survey.las")
    n, rec = summary["pulses_traced"], summary["pulses_recorded"]
    assert 0 < rec < n and rec == len(np.unique(np.asarray(las.gps_time)))
    assert f"{n} pulses, {rec} recorded ({n - rec} without a discrete return" in said


def test_a_damaged_cached_tile_is_traced_again(tmp_path):
    """A tile file cut short after its run (its record written) is traced again, not a traceback
    at the merge; the files are those of a run from scratch; the truth table is in GPS-time order
    as the points, though the sweeps cross the tiles back and forth."""
    write_obj(tmp_path / "plane.obj", tilted_plane(20.0, 1.0))
    kw = dict(altitude=300.0, length=6.0, quality={"rays_per_pulse": 64, "max_order": 1, "tile_m": 2.0},
              output={"truth": True})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scanner = {**SURVEY["scanner"], "pulse_rate_hz": 600.0, "scan_frequency_hz": 40.0}
        fly(tmp_path, PLANE, scanner, part=(0, 2), **kw)
        tile = next(next(p for p in tmp_path.iterdir() if p.name.startswith(".out.survey-")).glob("tile_*.parquet"))
        tile.write_bytes(tile.read_bytes()[:300])
        fly(tmp_path, PLANE, scanner, **kw)
        fly(tmp_path, PLANE, scanner, out="again", **kw)
    assert (tmp_path / "out" / "survey.las").read_bytes() == (tmp_path / "again" / "survey.las").read_bytes()
    truth = pd.read_parquet(tmp_path / "out" / "truth.parquet", columns=["gps_time"])["gps_time"].to_numpy()
    assert np.all(np.diff(truth) > 0)
    assert np.array_equal(truth, np.unique(np.asarray(laspy.read(tmp_path / "out" / "survey.las").gps_time)))


def test_force_never_deletes_the_scene_it_flies(tmp_path, capsys):
    """--out the folder holding SCENE.yaml, SURVEY.yaml and the mesh: refused even with --force."""
    sc, sv = _files(tmp_path)
    code, lines = _run(["survey", sc, sv, "--out", tmp_path, "--no-progress", "--force"], capsys)
    assert code == 1 and "holds the input" in lines[-1], lines
    assert sc.exists() and sv.exists() and (tmp_path / "plane.obj").exists()


def test_the_outputs_read_back(tmp_path, capsys):
    """LAS 1.4 PF9 + .wdp: laspy, `info` and the pulse reader agree with the summary."""
    sc, sv = _files(tmp_path)
    out = tmp_path / "out"
    code, _ = _run(["survey", sc, sv, "--out", out, "--no-progress"], capsys)
    assert code == 0
    summary = json.loads((out / "summary.json").read_text())
    las = laspy.read(out / "survey.las")
    assert las.header.version.major == 1 and las.header.version.minor == 4 and las.header.point_format.id == 9
    assert len(las.points) == summary["returns"] > 0
    assert len(np.unique(las.gps_time)) == summary["pulses_traced"]
    assert np.all(np.asarray(las.return_number) <= np.asarray(las.number_of_returns))
    assert np.abs(np.asarray(las.scan_angle) * 0.006).max() <= 2.0 + 1e-6
    assert any(v.record_id == 2112 for v in las.header.vlrs)  # OGC WKT CRS
    assert (out / "survey.wdp").stat().st_size > 0
    traj = (out / "trajectory.csv").read_text().splitlines()
    assert traj[0].startswith("gps_time,x,y,z,roll_deg,pitch_deg,heading_deg")
    capsys.readouterr()
    main(["info", str(out / "survey.las")])
    assert f"points:                {summary['returns']:,}" in capsys.readouterr().out
    main(["ingest", str(out / "survey.las"), "--trajectory", str(out / "trajectory.csv"),
          "--out", str(tmp_path / "pulses.parquet"), "--no-progress"])
    pulses = pd.read_parquet(tmp_path / "pulses.parquet")
    assert len(pulses) == summary["pulses_traced"]
    assert np.allclose(pulses["sensor_z"], 300.0) and np.allclose(pulses["sensor_x"], 0.0, atol=1e-6)
    # the range along the beam from the trajectory's sensor lands on the first discrete return
    for c in "xyz":
        first = np.array([v[0] for v in pulses[f"echo_{c}"]])
        assert np.allclose(pulses[f"sensor_{c}"] + pulses["range_m"] * pulses[f"dir_{c}"], first, atol=2e-3)


def test_an_independent_reader_puts_the_returns_on_the_plane(tmp_path):
    """The survey's LAS and .wdp read with the struct reader written from the LAS 1.4 R15 text
    (tests/reference_io.py): the waveforms are the pulse reader's, and every discrete return
    and each waveform's anchor-and-direction line meet the tilted plane flown (z = x tan 1 deg)."""
    from reference_io import RANGE_PER_NS, reference_pulses

    from waveforest.io.las.read import read_waveform_las

    write_obj(tmp_path / "plane.obj", tilted_plane(20.0, 1.0))
    scanner = {**SURVEY["scanner"], "pulse_rate_hz": 400.0, "gain": 0.08}  # 300 m: below full scale
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result, table, _, _ = fly(tmp_path, PLANE, scanner, altitude=300.0, length=6.0,
                                  quality={"rays_per_pulse": 256, "max_order": 1})
    assert result["saturated_pulses"] == 0
    las = tmp_path / "out" / "survey.las"
    ref = reference_pulses(las)
    ours = read_waveform_las(las)
    assert len(ref) == ours.num_rows == table.num_rows > 10
    tilt = np.tan(np.radians(1.0))
    for pulse, samples in zip(ref, ours.column("samples").to_pylist()):
        assert pulse["samples"] == [int(v) for v in samples]
        for x, y, z, t, _ in pulse["echoes"]:
            assert abs(z - x * tilt) < 0.03  # the discriminator's range on a plane: within 3 cm
            along = np.asarray(pulse["anchor"]) + np.asarray(pulse["dir"]) * t * RANGE_PER_NS
            assert np.allclose(along, (x, y, z), atol=1e-3)  # the point lies on its waveform's line


def test_clipped_waveforms_are_counted_and_named(tmp_path, capsys):
    """At 300 m the preset's gain drives the plane's echoes past 255 DN: the summary counts the
    pulses and the command says what to change, once, after its result line."""
    sc, sv = _files(tmp_path)
    code, lines = _run(["survey", sc, sv, "--out", tmp_path / "out", "--no-progress"], capsys)
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert code == 0 and summary["saturated_pulses"] == summary["pulses_traced"] > 0
    warn = [ln for ln in lines if ln.startswith("waveforest: warning:")]
    assert warn == [f"waveforest: warning: {summary['pulses_traced']} of {summary['pulses_traced']} pulses (100%) "
                    "reach the digitiser's full scale (255 DN): their waveforms are clipped and their discrete "
                    "returns early; lower scanner.gain (now 1) or fly higher"]


def test_resume_keeps_completed_tiles_and_parts_merge(tmp_path):
    """Part 0/2 leaves its tiles in the cache and no DIR; the full run then traces only the rest
    and writes the same files as a run from scratch."""
    write_obj(tmp_path / "plane.obj", tilted_plane(20.0, 1.0))
    scanner = SURVEY["scanner"]
    kw = dict(altitude=300.0, length=6.0, quality={"rays_per_pulse": 256, "max_order": 2, "tile_m": 2.0})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert fly(tmp_path, PLANE, scanner, part=(0, 2), **kw)[0] is None
        assert not (tmp_path / "out").exists()
        cache = [p for p in tmp_path.iterdir() if p.name.startswith(".out.survey-")]
        assert len(cache) == 1
        done = sorted(p.name for p in cache[0].glob("tile_*.json"))
        assert done and all(int(n[5:11]) % 2 == 0 for n in done)
        part = json.loads((cache[0] / "run_0_2_0.json").read_text())
        a, _, _, _ = fly(tmp_path, PLANE, scanner, **kw)
        assert not cache[0].exists()
        b, _, _, _ = fly(tmp_path, PLANE, scanner, out="again", **kw)
    assert a["tiles"] > 2 and a["pulses_traced"] == b["pulses_traced"]
    # the summary counts the part's run too: its wall time, and its memory if that was larger
    assert a["wall_s"] > part["wall_s"] > 0 and a["peak_memory_mb"] >= part["peak_memory_mb"] > 0
    assert 0 <= a["sigma_after_window"] < 1e-3  # two orders on a plane: nothing arrives late
    las = [(tmp_path / d / "survey.las").read_bytes() for d in ("out", "again")]
    assert las[0] == las[1]
    assert (tmp_path / "out" / "survey.wdp").read_bytes() == (tmp_path / "again" / "survey.wdp").read_bytes()
    assert cache_folder(tmp_path / "out", "k").parent == tmp_path


def test_plants_are_instances_of_a_bounded_set_of_prototypes(tmp_path):
    rows = ["species,x,y,height,seed"] + [f"fireweed,{i % 5},{i // 5},{0.5 + 0.1 * (i % 3)},{i}" for i in range(20)]
    (tmp_path / "plants.csv").write_text("\n".join(rows) + "\n")
    (tmp_path / "SCENE.yaml").write_text(yaml.safe_dump({"plants": {"table": "plants.csv", "prototype_seeds": 2,
                                                                      "height_step_m": 0.5}}))
    scene = load_scene(tmp_path / "SCENE.yaml")
    assert len(scene.plants) == 20 and len(scene.plants.prototypes) == 2  # one height, two seeds
    assert np.allclose(scene.plants.translation[:, :2], [[i % 5, i // 5] for i in range(20)])
    for row, expect in (("birch,0,0,nan,1", "column height, row 2: expected a finite number"),
                        ("birch,0,0,-5,1", "column height, row 2: expected a height above 0 m, got -5"),
                        ("birch,0,0,0.2,1", "row 2: height 0.2 m for birch: expected 0.5 to 12 m"),
                        ("birch,0,0,5,1.5", "column seed, row 2: expected a non-negative integer, got '1.5'")):
        (tmp_path / "plants.csv").write_text(f"species,x,y,height,seed\n{row}\n")
        with pytest.raises(SurveyError, match=expect):
            load_scene(tmp_path / "SCENE.yaml")


def test_the_plant_table_is_a_closed_set_of_columns(tmp_path, capsys):
    """A misnamed column (Z for z, rotation for rotation_deg) would be ignored silently: it is an
    error naming it; blanks after the commas are allowed; a header without rows is an error."""
    scene = {"plants": {"table": "plants.csv"}, "ground": {"type": "plane", "z": 0.0, "rho": 0.2}}
    (tmp_path / "plants.csv").write_text("species,x,y,height,seed,Z\nbirch,0,0,6,1,10\n")
    _fails(tmp_path, capsys, scene=scene, expect="plants.csv: unknown column(s) Z (expected species, x, y")
    (tmp_path / "plants.csv").write_text("species, x, y, height, seed\n")
    _fails(tmp_path, capsys, scene=scene, expect="plants.csv: no plant rows")
    (tmp_path / "plants.csv").write_text("species, x, y, height, seed, rotation_deg\nfireweed, 0, 0, 1.0, 1, 30\n")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _files(tmp_path, scene)
        assert load_scene(tmp_path / "SCENE.yaml").plants is not None


def test_plants_without_z_stand_on_the_ground(tmp_path):
    """No z column: each plant at the ground's height under it (a plane's z, a mesh's surface);
    a plant beyond the ground mesh is an error naming its row."""
    (tmp_path / "plants.csv").write_text("species,x,y,height,seed\nfireweed,0,0,1.0,1\nfireweed,10,-5,1.0,2\n")
    plane = {"plants": {"table": "plants.csv"}, "ground": {"type": "plane", "z": 312.5}}
    (tmp_path / "SCENE.yaml").write_text(yaml.safe_dump(plane))
    assert np.allclose(load_scene(tmp_path / "SCENE.yaml").plants.translation[:, 2], 312.5)
    write_obj(tmp_path / "slope.obj", tilted_plane(30.0, 20.0), material="default")  # z = x tan 20 deg
    (tmp_path / "SCENE.yaml").write_text(yaml.safe_dump({"plants": {"table": "plants.csv"},
                                                         "ground": {"type": "mesh", "file": "slope.obj"}}))
    z = load_scene(tmp_path / "SCENE.yaml").plants.translation[:, 2]
    assert np.allclose(z, [0.0, 10 * np.tan(np.radians(20.0))], atol=1e-4)
    (tmp_path / "plants.csv").write_text("species,x,y,height,seed\nfireweed,0,0,1.0,1\nfireweed,90,0,1.0,2\n")
    with pytest.raises(SurveyError, match="plants/table: row 3: .90, 0. lies beyond the ground mesh"):
        load_scene(tmp_path / "SCENE.yaml")


def test_the_workflow_inputs_are_the_files_the_yamls_name(tmp_path):
    """input_files (the Snakemake target's inputs): every mesh, the plant table, the trajectory;
    a YAML that cannot be read gives none."""
    from waveforest.survey.scene import input_files

    (tmp_path / "plants.csv").write_text("species,x,y,height,seed\nfireweed,0,0,1.0,1\n")
    write_obj(tmp_path / "roof.obj", tilted_plane(5.0, 10.0))
    write_obj(tmp_path / "dtm.obj", tilted_plane(50.0, 2.0), material="default")
    (tmp_path / "traj.csv").write_text("gps_time,x,y,z,roll_deg,pitch_deg,heading_deg\n0,0,0,500,0,0,0\n1,0,9,500,0,0,0\n")
    scene = {"objects": [{"file": "roof.obj", "materials": {"m": {"rho": 0.3}}}], "plants": {"table": "plants.csv"},
             "ground": {"type": "mesh", "file": "dtm.obj"}}
    (tmp_path / "SCENE.yaml").write_text(yaml.safe_dump(scene))
    (tmp_path / "SURVEY.yaml").write_text(yaml.safe_dump({"platform": {"trajectory": "traj.csv"}}))
    (tmp_path / "mats").mkdir()
    (tmp_path / "mats" / "roof.mtl").write_text("newmtl m\nhelios_reflectance 0.3\n")
    roof = tmp_path / "roof.obj"
    roof.write_text("mtllib mats/roof.mtl missing.mtl\n" + roof.read_text())
    files = input_files(tmp_path / "SCENE.yaml", tmp_path / "SURVEY.yaml")
    assert sorted(Path(f).name for f in files) == ["dtm.obj", "plants.csv", "roof.mtl", "roof.obj", "traj.csv"]
    (tmp_path / "SURVEY.yaml").write_text("platform: [")
    assert input_files(tmp_path / "SCENE.yaml", tmp_path / "SURVEY.yaml") == []


def test_rounded_heights_stay_within_their_species_range(tmp_path):
    """height_step_m rounds a height for its prototype, never past the species' range: a 3-m
    fireweed (its tallest) at a 0.4-m step is a 3-m prototype, not an error about 3.2 m."""
    (tmp_path / "plants.csv").write_text("species,x,y,height,seed\nfireweed,0,0,3.0,1\nfireweed,2,0,1.1,1\n")
    (tmp_path / "SCENE.yaml").write_text(yaml.safe_dump({"plants": {"table": "plants.csv", "height_step_m": 0.4}}))
    scene = load_scene(tmp_path / "SCENE.yaml")
    assert sorted(scene.plants.labels) == ["fireweed 1.2 m seed 1", "fireweed 3 m seed 1"]


def test_the_cache_key_follows_the_scene_content(tmp_path):
    """Tiles of an earlier run are reused only for the same triangles, properties and plants."""
    sc, sv_path = _files(tmp_path)
    cfg = config.load(None)
    sv = load_survey(sv_path, sensor_settings(cfg), reference_system(cfg))
    mcrt = survey_mcrt(mcrt_setup(cfg), sv)
    key = run_key(load_scene(sc), sv, mcrt, "")
    assert run_key(load_scene(sc), sv, mcrt, "") == key
    _files(tmp_path, scene={**PLANE, "objects": [{"file": "plane.obj", "materials": {"m": {"rho": 0.5}}}]})
    assert run_key(load_scene(sc), sv, mcrt, "") != key
    _files(tmp_path)
    write_obj(tmp_path / "plane.obj", tilted_plane(20.0, 2.0))
    assert run_key(load_scene(sc), sv, mcrt, "") != key


def test_a_full_disk_is_one_line_and_keeps_no_output(tmp_path, capsys, monkeypatch):
    """An OSError while writing (ENOSPC here) ends in one line; no output folder is left."""
    import errno

    import pyarrow.parquet as pq

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "x.parquet"))

    monkeypatch.setattr(pq, "write_table", full)
    sc, sv = _files(tmp_path)
    code, lines = _run(["survey", sc, sv, "--out", tmp_path / "out", "--no-progress"], capsys)
    assert code == 1 and len(lines) == 1 and "No space left on device" in lines[0], lines
    assert not (tmp_path / "out").exists()


def test_a_bad_part_is_a_usage_error(tmp_path, capsys):
    sc, sv = _files(tmp_path)
    code, lines = _run(["survey", sc, sv, "--out", tmp_path / "out", "--part", "2/2"], capsys)
    assert code == 2 and "'--part'" in lines[0] and "expected I/N with 0 <= I < N" in lines[0], lines
    assert not (tmp_path / "out").exists()


def test_a_merge_removes_stale_caches_of_its_folder(tmp_path, capsys):
    sc, sv = _files(tmp_path)
    stale = tmp_path / ".out.survey-0123456789abcdef"
    stale.mkdir()
    (stale / "tile_000000.json").write_text("{}")
    other = tmp_path / ".other.survey-0123456789abcdef"
    other.mkdir()
    code, _ = _run(["survey", sc, sv, "--out", tmp_path / "out", "--no-progress"], capsys)
    assert code == 0 and not stale.exists() and other.exists()


def test_ctrl_c_leaves_no_output_and_the_rerun_resumes(tmp_path, capsys, monkeypatch):
    """Interrupted after its first tile: exit 130, no DIR, that tile and the run's time kept; the
    rerun traces only the other tiles, counts both runs' time and writes what an uninterrupted
    run writes."""
    import waveforest.survey.run as run_module

    sc, sv = _files(tmp_path)
    real, calls = run_module.run_tile, []

    def first_then_interrupt(k, *args, **kwargs):
        if calls:
            raise KeyboardInterrupt
        calls.append(k)
        return real(k, *args, **kwargs)

    monkeypatch.setattr(run_module, "run_tile", first_then_interrupt)
    code, lines = _run(["survey", sc, sv, "--out", tmp_path / "out", "--no-progress"], capsys)
    assert code == 130 and not (tmp_path / "out").exists(), lines
    cache = next(tmp_path.glob(".out.survey-*"))
    assert [p.name for p in cache.glob("tile_*.json")] == [f"tile_{calls[0]:06d}.json"]
    interrupted = json.loads((cache / "run_0_1_0.json").read_text())  # its time counts in the summary

    def counting(k, *args, **kwargs):
        calls.append(k)
        return real(k, *args, **kwargs)

    monkeypatch.setattr(run_module, "run_tile", counting)
    code, _ = _run(["survey", sc, sv, "--out", tmp_path / "out", "--no-progress"], capsys)
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert code == 0 and calls[0] not in calls[1:] and len(calls) == summary["tiles"]
    assert summary["wall_s"] > interrupted["wall_s"] > 0
    code, _ = _run(["survey", sc, sv, "--out", tmp_path / "again", "--no-progress"], capsys)
    assert (tmp_path / "out" / "survey.wdp").read_bytes() == (tmp_path / "again" / "survey.wdp").read_bytes()


def test_obj_faces_materials_and_indices(tmp_path):
    """Triangles and a quad (fanned, file order), v/vt/vn corners, relative indices, comments
    after a line's values, materials from the MTL (helios_reflectance) and from SCENE.yaml, and a
    face before any usemtl."""
    from waveforest.survey.scene import read_obj

    (tmp_path / "a.mtl").write_text("newmtl bark\nhelios_reflectance 0.25\nnewmtl leaf\nKd 1 1 1\n")
    (tmp_path / "a.obj").write_text(
        "mtllib a.mtl\nv 0 0 0\nv 1 0 0  # a comment after the numbers\nv 1 1 0\nv 0 1 0\n"
        "f 1 2 3 # and after a face\n"            # no usemtl yet: material "default"
        "usemtl bark\nf 1/1/1 2/2/2 3/3/3 4/4/4\n"  # a quad: (1 2 3), (1 3 4)
        "usemtl leaf\nv 0 0 5\nv 1 0 5\nv 0 1 5\nf -3 -2 -1\n")
    props = {"leaf": {"rho": 0.4, "tau": 0.5, "kind": "leaf"}, "default": {"rho": 0.1}}
    sc = read_obj(tmp_path / "a.obj", props, "S")
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 5], [1, 0, 5], [0, 1, 5]], float)
    want = v[[[0, 1, 2], [0, 1, 2], [0, 2, 3], [4, 5, 6]]]
    assert np.array_equal(sc.triangles, want.astype(np.float32))
    assert np.allclose(np.asarray(sc.rho) * np.ones(4), [0.1, 0.25, 0.25, 0.4])
    assert np.allclose(np.asarray(sc.tau) * np.ones(4), [0, 0, 0, 0.5])
    assert list(np.asarray(sc.kind) * np.ones(4, int)) == [3, 3, 3, 1]
    with pytest.raises(SurveyError, match="material 'leaf' has no optical properties"):
        read_obj(tmp_path / "a.obj", {"default": {"rho": 0.1}}, "S")
    (tmp_path / "a.mtl").write_text("newmtl\tbark\nhelios_reflectance\t0.25\nhelios_specularity 0.2\n")  # tabs too
    with pytest.warns(UserWarning, match=r"a.mtl: helios_specularity \(line 3\): not used"):
        assert np.allclose(read_obj(tmp_path / "a.obj", props, "S").rho[1], 0.25)
    for bad, got in (("1.5", "'1.5'"), ("abc", "'abc'"), ("", "no value")):
        (tmp_path / "a.mtl").write_text(f"newmtl bark\nhelios_reflectance {bad}\n")
        with pytest.raises(SurveyError, match=f"a.mtl: line 2: helios_reflectance of material 'bark': "
                                              f"expected a number in \\[0, 1\\], got {got}"):
            read_obj(tmp_path / "a.obj", props, "S")
    (tmp_path / "a.mtl").unlink()
    with pytest.raises(SurveyError, match="material 'bark' has no .*; its MTL file a.mtl does not exist"):
        read_obj(tmp_path / "a.obj", props, "S")


def test_a_bare_ply_needs_its_default_material(tmp_path, capsys):
    """A PLY from another tool (no per-face rho, tau, kind): an error that names the fix, and with
    the object's material ``default`` every face takes it."""
    (tmp_path / "bare.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
        "-20 -20 0\n20 -20 0.7\n20 20 0.7\n-20 20 0\n4 0 1 2 3\n")
    scene = {"objects": [{"file": "bare.ply"}], "ground": {"type": "none"}}
    _fails(tmp_path, capsys, scene=scene, expect="bare.ply: face property rho, tau, kind missing (expected rho, "
                                                  "tau, kind); or set this object's materials/default/rho")
    scene["objects"][0]["materials"] = {"default": {"rho": 0.35, "kind": "ground"}}
    (tmp_path / "SCENE.yaml").write_text(yaml.safe_dump(scene))
    sc = load_scene(tmp_path / "SCENE.yaml").static
    assert len(sc) == 2 and np.allclose(sc.rho, 0.35) and np.all(np.asarray(sc.kind) == 0)
    (tmp_path / "SCENE.yaml").write_text(yaml.safe_dump({"ground": {"type": "mesh", "file": "bare.ply", "rho": 0.2}}))
    sc = load_scene(tmp_path / "SCENE.yaml").static  # a bare terrain mesh takes ground/rho
    assert len(sc) == 2 and np.allclose(sc.rho, 0.2) and np.all(np.asarray(sc.kind) == 0)


def test_a_scanner_without_preset_needs_every_value(tmp_path, capsys):
    survey = {**SURVEY, "scanner": {"preset": None, "pulse_rate_hz": 40.0}}
    _fails(tmp_path, capsys, survey=survey, expect="SURVEY.yaml: scanner/pattern: expected a value")
    survey = {**SURVEY, "scanner": {**SURVEY["scanner"], "bits": 12}}
    _fails(tmp_path, capsys, survey=survey, expect="scanner/bits:")


def test_a_ground_mesh_is_ground(tmp_path):
    write_obj(tmp_path / "g.obj", tilted_plane(10.0, 5.0), material="soil")
    (tmp_path / "g.mtl").write_text("newmtl soil\nhelios_reflectance 0.2\n")
    text = (tmp_path / "g.obj").read_text()
    (tmp_path / "g.obj").write_text("mtllib g.mtl\n" + text)
    (tmp_path / "SCENE.yaml").write_text(yaml.safe_dump({"ground": {"type": "mesh", "file": "g.obj"}}))
    scene = load_scene(tmp_path / "SCENE.yaml")
    assert np.all(np.asarray(scene.static.kind) == 0) and np.allclose(scene.static.rho, 0.2)


def test_the_ray_budget_is_the_config_s_unless_the_survey_fixes_it(tmp_path):
    """quality.rays_per_pulse fixes the rays; else quality.tolerance or the config's mcrt.tolerance
    sets the adaptive budget, and the summary counts the rays each pulse used."""
    cfg = config.load(None)
    sc, sv_path = _files(tmp_path, survey={**SURVEY, "quality": {"max_order": 2, "tile_m": 2.0}})
    sv = load_survey(sv_path, sensor_settings(cfg), reference_system(cfg))
    assert survey_mcrt(mcrt_setup(cfg), sv).tolerance == cfg["mcrt"]["tolerance"]
    _files(tmp_path, survey={**SURVEY, "quality": {"tolerance": 0.5, "tile_m": 2.0}})
    assert survey_mcrt(mcrt_setup(cfg), load_survey(sv_path, sensor_settings(cfg), reference_system(cfg))).tolerance == 0.5
    fixed = survey_mcrt(mcrt_setup(cfg), load_survey(_files(tmp_path)[1], sensor_settings(cfg), reference_system(cfg)))
    assert fixed.tolerance is None and fixed.n_rays == 256

    result, _, _, _ = fly(tmp_path, {"objects": [{"file": "plane.obj", "materials": {"m": {"rho": 0.4}}}],
                                     "ground": {"type": "none"}}, {"pulse_rate_hz": 200.0, "scan_angle_deg": 1.0},
                          altitude=300.0, length=1.0, quality={"rays_per_pulse": None, "tolerance": 0.5})
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["tolerance"] == 0.5 and summary["rays_per_pulse"] is None
    n = summary["pulses_traced"]
    assert n > 0 and cfg["mcrt"]["min_rays"] * n <= summary["rays"] <= cfg["mcrt"]["max_rays"] * n


def test_seed_option_overrides_the_survey_file_s_seed(tmp_path, capsys):
    """--seed N replaces SURVEY.yaml's seed: the file's own seed given as --seed writes the same
    bytes as no option, and another seed changes the waveforms."""
    sc, sv = _files(tmp_path, survey={**SURVEY, "seed": 4})
    files = {}
    for name, extra in (("file", []), ("same", ["--seed", "4"]), ("other", ["--seed", "5"])):
        code, lines = _run(["survey", sc, sv, "--out", tmp_path / name, "--no-progress", *extra], capsys)
        assert code == 0, lines
        files[name] = [(tmp_path / name / f).read_bytes() for f in ("survey.las", "survey.wdp")]
    assert files["same"] == files["file"]
    assert files["other"][1] != files["file"][1]


@pytest.mark.parametrize("gain", [1.0, 2.0])
def test_the_agc_of_the_scanner_s_gain_reads_back(tmp_path, gain):
    """Every point's user_data holds the AGC whose gain under the law of Eq. 1 is the scanner's
    gain (within half an AGC step); the reader takes it without warning that AGC is missing."""
    write_obj(tmp_path / "plane.obj", tilted_plane(20.0, 1.0))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        _, table, sv, _ = fly(tmp_path, PLANE, {**SURVEY["scanner"], "gain": gain}, altitude=300.0, length=2.0,
                              quality={"rays_per_pulse": 256, "max_order": 1})
    assert not [w for w in caught if "AGC" in str(w.message)], [str(w.message) for w in caught]
    sc = sv.scanner
    assert (sc.agc_law_a, sc.agc_law_b) == AGC_LAW
    agc = table.column("agc").to_numpy()
    assert len(agc) > 0 and np.all(agc == sc.agc)
    assert np.all(np.asarray(laspy.read(tmp_path / "out" / "survey.las").user_data) == sc.agc)
    assert abs(1 + (sc.agc - sc.agc_law_a) * sc.agc_law_b - gain) <= sc.agc_law_b / 2


def test_an_agc_beyond_the_8_bit_register_is_clipped(tmp_path):
    """A gain whose AGC would fall outside 1..255 records the nearest end."""
    cfg = config.load(None)
    survey = {**SURVEY, "scanner": {**SURVEY["scanner"], "gain": 100.0}}
    sv = load_survey(_files(tmp_path, survey=survey)[1], sensor_settings(cfg), reference_system(cfg))
    assert sv.scanner.agc == 255
    survey = {**SURVEY, "scanner": {**SURVEY["scanner"], "gain": 1e-3, "agc_law_a": 3.0}}
    sv = load_survey(_files(tmp_path, survey=survey)[1], sensor_settings(cfg), reference_system(cfg))
    assert sv.scanner.agc == 1


def test_tiles_are_widened_under_the_adaptive_budget_only(tmp_path):
    """plan(min_tile_pulses) widens the tiles by an integer factor until they hold that many pulses
    on average; every pulse's ground point stays in its tile; without it the tiles are tile_m."""
    assert tile_side(10.0, 1000, 10, 256) == 20.0 and tile_side(10.0, 3000, 10, 256) == 10.0
    assert tile_side(2.0, 90, 10, 256) == 12.0  # 9 per tile: factor ceil(sqrt(256 / 9)) = 6
    cfg = config.load(None)
    sc, sv_path = _files(tmp_path, survey={**SURVEY, "scanner": {**SURVEY["scanner"], "pulse_rate_hz": 400.0}})
    scene, sv = load_scene(sc), load_survey(sv_path, sensor_settings(cfg), reference_system(cfg))
    fixed, wide = plan(scene, sv), plan(scene, sv, 64)
    assert fixed.tile_m == sv.tile_m and len(wide.pulses) == len(fixed.pulses)
    assert wide.tile_m > sv.tile_m and len(wide.tiles) < len(fixed.tiles)
    f, mean = round(wide.tile_m / sv.tile_m), len(fixed.pulses) / len(fixed.tiles)
    assert mean < 64 and (f - 1) ** 2 * mean < 64 <= f**2 * mean  # the smallest factor
    for pl in (fixed, wide):
        p = pl.pulses
        ground = p.origin + ((pl.ground_z - p.origin[:, 2]) / p.direction[:, 2])[:, None] * p.direction
        lo = pl.tile_xy[np.searchsorted(pl.tiles, pl.tile)]
        assert np.all((ground[:, :2] >= lo - 1e-9) & (ground[:, :2] < lo + pl.tile_m + 1e-9))
