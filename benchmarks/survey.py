"""`waveforest survey`: physics against exact answers, and a user's stand (speed, memory).

Physics (the scenes and answers of tests/test_survey_physics.py, flown end to end and read
back from the LAS; ``name: value unit``):

* ``plane_nadir_energy_error_pct``, ``plane_nadir_range_bias_cm`` (largest |error| over the pulses);
  ``plane_offnadir20_...`` the same at 20 deg (conic scan): energy against
  G integral(S) rho cos(theta) / (pi R^2), range against the plane along the beam;
* ``tilted30_sigma_sd_error_pct``: SD of sigma(t) against 2 sd tan(alpha) / c; ``tilted30_fwhm_error_pct``;
* ``step_upper_share_error_pct``, ``step_echo_range_error_cm``: the plateau's share of sigma
  against Phi(x0 / sd); both discrete returns against the plateau and the ground.

Memory of the 1-ha stand (``--memory-only``): the whole scene (every prototype built and
given its BVH) and the tile in the middle of the stand given its BVH, without tracing:
``memory_prototypes``, ``memory_tile_triangles``, ``memory_peak_mb``.

Stand (``--area-ha``, default 0.01 ha; ``--full`` = 1 ha): mixed birch, raspberry and fireweed
(birches 4-12 m one per 25 m^2, raspberry and fireweed plots of 6 m on a 6-m grid), flat
ground; one leg with the als60 preset slowed to 5 pulses/m^2; default quality (the config's
mcrt section) unless ``--rays``/``--orders``. Figures: ``stand_pulses``,
``stand_prototypes``, ``stand_cpu_ms_per_pulse``, ``stand_wall_s``, ``stand_peak_mb``,
``stand_1ha_minutes_2_cores`` (CPU per pulse x 50,000 pulses / 2 cores, plus the prototype
build), ``stand_pulses_per_s``.

The adaptive ray budget against a fixed one (``--adaptive``): ``examples/survey`` (5 orders)
with its leg cut to ``--leg-m`` m over the plot, flown at 4,096 fixed rays, at the budget
(``quality.tolerance`` 0.2) in the planned tiles (widened to ``ADAPTIVE_TILE_PULSES`` pulses)
and at the budget in tiles of ``quality.tile_m``, in one run: ``<case>_cpu_us_per_ray``,
``<case>_wall_s``, ``<case>_rays_per_pulse``, ``<case>_queries_per_ray`` (Embree nearest-hit and
visibility queries per emitted ray: the orders above the first) and ``<case>_cpu_us_per_query``.

    python benchmarks/survey.py [--area-ha 0.01] [--rays N] [--orders K] [--full] [--no-physics] [--memory-only]
    python benchmarks/survey.py --adaptive [--leg-m 10]
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the test fixtures live in tests/fixtures
from fixtures.survey import (
    FWHM_PER_SD,
    fly,
    gaussian_energy,
    step,
    tilted_plane,
    waveform_energy,
    write_obj,
)
from scipy.special import erf

import waveforest.survey.run as survey_run
from waveforest import config
from waveforest.constants import C_M_PER_NS, RANGE_PER_NS
from waveforest.mcrt.backends.base import RayQueries
from waveforest.settings import mcrt_setup, reference_system, sensor_settings
from waveforest.survey import load_scene, load_survey, run_survey, sensor_setup, survey_mcrt
from waveforest.survey.engine import TileScenes
from waveforest.survey.run import peak_memory_mb

QUIET = {"pulse_rate_hz": 50.0, "scan_frequency_hz": 1.7, "bits": 16, "noise_sd": 0.01}


def echo(table, k):
    return np.array([v[k] for v in table.column("echo_z").to_pylist()])


def physics(tmp: Path) -> None:
    for theta in (0.0, 20.0):
        d = tmp / f"plane{theta:g}"
        d.mkdir()
        scene = {"ground": {"type": "plane", "z": 0.0, "rho": 0.3, "extent": [-600, -600, 600, 600]}}
        sc = {**QUIET, "pattern": "conic" if theta else "oscillating", "scan_angle_deg": theta, "gain": 100.0}
        _, t, sv, _ = fly(d, scene, sc, altitude=1000.0, length=20.0, quality={"rays_per_pulse": 4096})
        cos = math.cos(math.radians(theta))
        expected = gaussian_energy(sv) * 0.3 * cos / math.pi / (1000.0 / cos) ** 2
        e = waveform_energy(t, sv.scanner.noise_mean) / expected - 1
        name = "plane_nadir" if theta == 0 else "plane_offnadir20"
        print(f"{name}_pulses: {t.num_rows} pulses")
        print(f"{name}_energy_error_pct: {100 * np.abs(e).max():.3f} %")
        print(f"{name}_range_bias_cm: {100 * np.abs(echo(t, 0) / cos).max():.2f} cm")
    d = tmp / "tilted"
    d.mkdir()
    write_obj(d / "plane.obj", tilted_plane(30.0, 30.0))
    scene = {"objects": [{"file": "plane.obj", "materials": {"m": {"rho": 0.4}}}], "ground": {"type": "none"}}
    _, t, sv, _ = fly(d, scene, {**QUIET, "scan_angle_deg": 0.0, "divergence_mrad": 5.0}, altitude=300.0,
                      length=20.0, quality={"rays_per_pulse": 4096}, output={"truth": True})
    sd_t = 2 * 300.0 * 5e-3 / (2 * math.sqrt(2)) * math.tan(math.radians(30.0)) / C_M_PER_NS
    errs, fwhm_errs = [], []
    expected_fwhm = math.hypot(sv.scanner.pulse_fwhm_ns, FWHM_PER_SD * sd_t)
    for row in pq.read_table(d / "out" / "truth.parquet").to_pylist():
        s = np.asarray(row["sigma_order_1"])
        tt = row["t0_ns"] + (np.arange(len(s)) + 0.5) * row["bin_ns"]
        m = (s * tt).sum() / s.sum()
        errs.append(math.sqrt((s * (tt - m) ** 2).sum() / s.sum()) / sd_t - 1)
    for samples, dt in zip(t.column("samples").to_pylist(), t.column("sampling_ns").to_numpy()):
        v = np.asarray(samples, float) - sv.scanner.noise_mean
        fine = np.arange(0, (len(v) - 1) * dt, 0.01)
        w = np.interp(fine, np.arange(len(v)) * dt, v)
        above = fine[w >= w.max() / 2]
        fwhm_errs.append((above[-1] - above[0]) / expected_fwhm - 1)
    print(f"tilted30_sigma_sd_error_pct: {100 * np.abs(errs).max():.3f} %")
    print(f"tilted30_fwhm_error_pct: {100 * np.abs(fwhm_errs).max():.2f} %")
    d = tmp / "step"
    d.mkdir()
    write_obj(d / "step.obj", step(30.0, 0.0, 3.0))
    scene = {"objects": [{"file": "step.obj", "materials": {"m": {"rho": 0.4}}}], "ground": {"type": "none"}}
    _, t, _, _ = fly(d, scene, {**QUIET, "scan_angle_deg": 0.0, "divergence_mrad": 5.0}, x=0.3, altitude=300.0,
                     length=20.0, quality={"rays_per_pulse": 4096}, output={"truth": True})
    sd_m = 300.0 * 5e-3 / (2 * math.sqrt(2))
    share = 0.5 * (1 + erf(0.3 / (sd_m * math.sqrt(2))))
    errs = []
    for row in pq.read_table(d / "out" / "truth.parquet").to_pylist():
        s = np.asarray(row["sigma_order_1"])
        tt = row["t0_ns"] + (np.arange(len(s)) + 0.5) * row["bin_ns"]
        errs.append(s[tt * RANGE_PER_NS < 300.0 - 1.5].sum() / s.sum() / share - 1)
    print(f"step_upper_share_error_pct: {100 * np.abs(errs).max():.3f} %")
    print(f"step_two_echoes_fraction: {np.mean(t.column('n_echoes').to_numpy() == 2):.3f}")
    rng_err = max(np.abs(echo(t, 0) - 3.0).max(), np.abs(echo(t, 1)).max())
    print(f"step_echo_range_error_cm: {100 * rng_err:.2f} cm")


def stand_files(tmp: Path, side: float, seed: int = 5) -> None:
    """plants.csv and SCENE.yaml of a mixed stand of ``side`` x ``side`` m centred on (0, 0)."""
    rng = np.random.default_rng(seed)
    rows = ["species,x,y,height,seed,rotation_deg"]
    n_birch = max(1, round(side * side / 25.0))
    for i in range(n_birch):
        x, y = rng.uniform(-side / 2, side / 2, 2)
        rows.append(f"birch,{x:.2f},{y:.2f},{rng.uniform(4, 12):.2f},{i},{rng.uniform(0, 360):.0f}")
    grid = np.arange(-side / 2 + 3.0, side / 2, 6.0)
    k = 0
    for gx in grid:
        for gy in grid:
            sp = "raspberry" if k % 2 else "fireweed"
            rows.append(f"{sp},{gx:.2f},{gy:.2f},{rng.uniform(0.5, 1.6):.2f},{k},{rng.uniform(0, 360):.0f}")
            k += 1
    (tmp / "plants.csv").write_text("\n".join(rows) + "\n")


def stand(tmp: Path, area_ha: float, rays, orders) -> None:
    side = math.sqrt(area_ha * 1e4)
    stand_files(tmp, side)
    scene = {"plants": {"table": "plants.csv"}, "ground": {"type": "plane", "z": 0.0, "rho": 0.3, "margin_m": 0.0}}
    # 5 pulses/m^2 with the als60 preset: 120 kHz over a 2 H tan(15 deg) swath at speed v
    altitude = 1200.0
    speed = 120_000.0 / (5.0 * 2 * altitude * math.tan(math.radians(15.0)))
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res, table, sv, _ = fly(tmp, scene, {}, altitude=altitude, length=side, speed=speed,
                                quality={"rays_per_pulse": rays, "max_order": orders}, progress=True)
    wall = time.perf_counter() - t0
    n = res["pulses_traced"]
    print(f"stand_area_ha: {area_ha:g} ha")
    print(f"stand_pulses: {n} pulses")
    print(f"stand_returns: {res['returns']} returns")
    print(f"stand_rays_per_pulse: {res['rays'] / n:.0f} rays")  # mean: the adaptive budget varies them
    print(f"stand_max_order: {res['max_order']} orders")
    print(f"stand_prototypes: {res['prototypes']} prototypes")
    print(f"stand_prototype_build_s: {res['prototype_build_s']:.1f} s")
    print(f"stand_cpu_ms_per_pulse: {res['cpu_ms_per_pulse']:.1f} ms")
    print(f"stand_wall_s: {wall:.1f} s")
    print(f"stand_pulses_per_s: {n / wall:.2f} pulses/s")
    print(f"stand_peak_mb: {res['peak_memory_mb']:.0f} MB")
    minutes = (res["cpu_ms_per_pulse"] * 1e-3 * 50_000 / 2 + res["prototype_build_s"]) / 60
    print(f"stand_1ha_minutes_2_cores: {minutes:.1f} min")


def stand_memory(tmp: Path, area_ha: float, seeds: int) -> None:
    """Peak memory of a stand's scene without tracing: every prototype built and prepared, and
    the tile with the most plant copies given its BVH (the survey holds one tile at a time)."""
    side = math.sqrt(area_ha * 1e4)
    stand_files(tmp, side)
    (tmp / "SCENE.yaml").write_text(f"plants: {{table: plants.csv, prototype_seeds: {seeds}}}\n"
                                    "ground: {type: plane, z: 0.0, rho: 0.3, margin_m: 0.0}\n")
    cfg = config.load(None)
    t = time.process_time()
    scene = load_scene(tmp / "SCENE.yaml")
    (tmp / "SURVEY.yaml").write_text(f"platform: {{legs: [{{start: [0, {-side / 2}], end: [0, {side / 2}]}}]}}\n")
    sv = load_survey(tmp / "SURVEY.yaml", sensor_settings(cfg), reference_system(cfg))
    mcrt = survey_mcrt(mcrt_setup(cfg), sv)
    tiles = TileScenes(scene, sv, mcrt.viewed_diameter_m, math.tan(math.radians(sv.scanner.scan_angle_deg)))
    build_s = time.process_time() - t
    lo = scene.bounds[0, :2]
    centre = lo + sv.tile_m * np.floor((np.array([0.0, 0.0]) - lo) / sv.tile_m)
    t = time.process_time()
    prepared = tiles.build(centre, 1000, mcrt.n_rays)
    print(f"memory_area_ha: {area_ha:g} ha")
    print(f"memory_plants: {len(scene.plants)} plants")
    print(f"memory_prototypes: {len(scene.plants.prototypes)} prototypes")
    print(f"memory_prototype_triangles: {sum(len(p) for p in scene.plants.prototypes)} triangles")
    print(f"memory_prototype_build_s: {build_s:.1f} s")
    print(f"memory_tile_triangles: {len(prepared)} triangles")
    print(f"memory_tile_build_s: {time.process_time() - t:.1f} s")
    print(f"memory_peak_mb: {peak_memory_mb():.0f} MB")


EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "survey"


def adaptive(tmp: Path, leg_m: float) -> None:
    """CPU per ray of the example survey at a fixed budget and at the adaptive budget (module docstring)."""
    import shutil

    import yaml

    for f in EXAMPLE.iterdir():
        shutil.copy(f, tmp / f.name)
    doc = yaml.safe_load((EXAMPLE / "SURVEY.yaml").read_text())
    leg = doc["platform"]["legs"][0]
    leg["end"] = [leg["start"][0], leg["start"][1] + 32.0 + leg_m]  # the plot starts 32 m after the leg's start
    leg["start"] = [leg["start"][0], leg["start"][1] + 32.0]
    cfg = config.load(None)
    sensor = sensor_settings(cfg)
    scene = load_scene(tmp / "SCENE.yaml")
    queries = [0]
    intersect, occluded = RayQueries.intersect, RayQueries.occluded

    def count(method):
        def wrapped(self, origins, *args, **kwargs):
            queries[0] += len(origins)
            return method(self, origins, *args, **kwargs)
        return wrapped

    RayQueries.intersect, RayQueries.occluded = count(intersect), count(occluded)
    widened = survey_run.ADAPTIVE_TILE_PULSES
    try:
        for case, quality, min_pulses in (("fixed4096", {"rays_per_pulse": 4096}, widened),
                                          ("adaptive", {"tolerance": 0.2}, widened),
                                          ("adaptive_tile_m", {"tolerance": 0.2}, 1)):
            doc["quality"] = {"max_order": 5, "tile_m": 10.0, **quality}
            (tmp / f"{case}.yaml").write_text(yaml.safe_dump(doc))
            sv = load_survey(tmp / f"{case}.yaml", sensor, reference_system(cfg))
            survey_run.ADAPTIVE_TILE_PULSES = min_pulses
            queries[0] = 0
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                r = run_survey(scene, sv, survey_mcrt(mcrt_setup(cfg), sv), sensor_setup(sv, sensor), tmp / case)
            print(f"{case}_pulses: {r['pulses_traced']} pulses")
            print(f"{case}_tiles: {r['tiles']} tiles")
            print(f"{case}_rays_per_pulse: {r['rays'] / r['pulses_traced']:.0f} rays")
            print(f"{case}_cpu_ms_per_pulse: {r['cpu_ms_per_pulse']:.1f} ms")
            print(f"{case}_cpu_us_per_ray: {1e6 * r['cpu_s'] / r['rays']:.2f} us")
            print(f"{case}_queries_per_ray: {queries[0] / r['rays']:.2f} queries")
            print(f"{case}_cpu_us_per_query: {1e6 * r['cpu_s'] / queries[0]:.3f} us")
            print(f"{case}_wall_s: {r['wall_s']:.1f} s", flush=True)
    finally:
        RayQueries.intersect, RayQueries.occluded = intersect, occluded
        survey_run.ADAPTIVE_TILE_PULSES = widened


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--area-ha", type=float, default=0.01, help="stand area, ha (default 0.01)")
    ap.add_argument("--full", action="store_true", help="the full 1-ha stand (about 50,000 pulses)")
    ap.add_argument("--rays", type=int, default=None, help="rays per pulse (default: the config's)")
    ap.add_argument("--orders", type=int, default=None, help="highest order (default: the config's)")
    ap.add_argument("--no-physics", action="store_true", help="only the stand")
    ap.add_argument("--no-stand", action="store_true", help="only the physics")
    ap.add_argument("--prototype-seeds", type=int, default=3, help="SCENE.yaml plants/prototype_seeds (--memory-only)")
    ap.add_argument("--memory-only", action="store_true",
                    help="only the scene of a 1-ha stand (--area-ha to change): prototypes and the largest tile, "
                         "no tracing; peak memory")
    ap.add_argument("--adaptive", action="store_true", help="only the adaptive budget against a fixed one")
    ap.add_argument("--leg-m", type=float, default=10.0, help="--adaptive: leg length over the plot, m (default 10)")
    a = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="survey_bench_") as tmp:
        tmp = Path(tmp)
        if a.adaptive:
            adaptive(tmp, a.leg_m)
            return
        if a.memory_only:
            stand_memory(tmp, 1.0 if a.area_ha == 0.01 else a.area_ha, a.prototype_seeds)
            return
        if not a.no_stand:  # first: the process's peak memory is the stand's
            (tmp / "stand").mkdir()
            stand(tmp / "stand", 1.0 if a.full else a.area_ha, a.rays, a.orders)
        if not a.no_physics:
            physics(tmp)


if __name__ == "__main__":
    main()
