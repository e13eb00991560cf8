"""Sensitivity of simulated birch Apeak to vegetation parameters (docs/method.md §(i2), Fig. 8).

A birch crown of ``sensitivity.height_m`` (3 m) without ground, seen at nadir from
``range_m`` (1200 m) with the reference sensor (S(t) of 2010_12_1 or its Gaussian stand-in,
:mod:`.reference`), 1-ns sampling, footprint = divergence x range (0.15 mrad -> 0.18 m); the
sensor XY jittered uniformly within +-``xy_jitter_m`` (0.30 m) of the stem. One parameter at
a time is swept: mean leaf inclination angle (``build_scene(mean_leaf_angle=...)``), leaf rho,
leaf tau, and the scale on each leaf's area; plus the baseline (the species model as is:
spherical LAD, rho 0.47, tau 0.50, scale 1).

Per setting: ``pulses`` pulses spread evenly over ``instances`` birch instances. Common random
numbers: instance k has the same seed (structure), the same beam positions and the same MCRT
and noise streams in every setting, so the curves show the parameter's effect with little
Monte Carlo noise between neighbouring values. Output per setting: mean Apeak of the pulses
with a CFD echo and its standard error (SD / sqrt(n)); pulses without an echo (the beam
missed the crown: no ground) are counted but have no Apeak.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import click
import numpy as np
import pandas as pd
import pyarrow as pa

from waveforest.atomic import atomic_path
from waveforest.cliutil import reference_sensor_options
from waveforest.constants import RANGE_PER_NS
from waveforest.io.pulses import write_table
from waveforest.mcrt import Beams
from waveforest.mcrt.threads import default_threads
from waveforest.model.forward import MCRTSetup, SensorSetup, trace_and_render
from waveforest.report import plots
from waveforest.rng import hashed_seed63, hashed_sequence
from waveforest.sensor.reference import reference_sensor
from waveforest.vegetation import build_scene
from waveforest.workers import unordered_map

PARAMETERS = ("mean_leaf_angle_deg", "leaf_rho", "leaf_tau", "leaf_area_scale")
"""Swept parameters (config keys of ``sensitivity``) in the order of Fig. 8."""

_BUILD_KWARG = {"mean_leaf_angle_deg": "mean_leaf_angle", "leaf_rho": "leaf_rho", "leaf_tau": "leaf_tau",
                "leaf_area_scale": "leaf_area_scale"}


def settings(cfg: dict) -> list[tuple[str, float, dict]]:
    """(parameter, value, build_scene keyword arguments) of every setting, baseline first."""
    s = cfg["sensitivity"]
    out = [("baseline", np.nan, {})]
    for p in PARAMETERS:
        for v in s[p]:
            out.append((p, float(v), {_BUILD_KWARG[p]: float(v)}))
    return out


@dataclass(frozen=True)
class Geometry:
    """Nadir beams of the study: one per pulse, instance index and sensor offset."""

    instance: np.ndarray  # (n,) int64
    origin: np.ndarray  # (n, 3) float64, m (scene coordinates, ground level z = 0)
    direction: np.ndarray  # (n, 3)
    range_m: np.ndarray  # (n,)


def geometry(cfg: dict) -> Geometry:
    """The pulses' beams (the same in every setting)."""
    s = cfg["sensitivity"]
    n, k = int(s["pulses"]), int(s["instances"])
    rng = np.random.default_rng(hashed_sequence(int(cfg["seed"]), "sensitivity", "geometry"))
    jitter = rng.uniform(-float(s["xy_jitter_m"]), float(s["xy_jitter_m"]), (n, 2))
    r = float(s["range_m"])
    origin = np.column_stack([jitter, np.full(n, r)])
    direction = np.tile([0.0, 0.0, -1.0], (n, 1))
    return Geometry(np.arange(n) % k, origin, direction, np.full(n, r))


def simulate_setting(build_kwargs: dict, geom: Geometry, setup: SensorSetup, mcrt: MCRTSetup, cfg: dict,
                     threads: int | None = None, scene_builder=None) -> pd.DataFrame:
    """Simulate every pulse of one setting; one row per pulse (instance, Apeak, FWHM, E, Npeaks, H).

    The instances are shared over ``threads`` worker threads (:func:`waveforest.workers.unordered_map`);
    the rows do not depend on it.

    ``scene_builder``: ``f(species, height, seed, **kwargs) -> Scene`` (default
    :func:`waveforest.vegetation.build_scene`).
    """
    if scene_builder is None:
        scene_builder = build_scene

    s = cfg["sensitivity"]
    seed = int(cfg["seed"])
    workers = threads if threads is not None else default_threads()

    def instance(k):
        idx = np.flatnonzero(geom.instance == k)
        scene = scene_builder("birch", float(s["height_m"]), hashed_seed63(seed, "sensitivity", "scene", int(k)),
                            ground=False, lai_jitter=float(cfg["vegetation"]["lai_jitter"]), **build_kwargs)
        beams = Beams.from_divergence(geom.origin[idx], geom.direction[idx], float(s["divergence_mrad"]),
                                      geom.range_m[idx])
        ss = hashed_sequence(seed, "sensitivity", "pulses", int(k))
        trace_seed = int(ss.generate_state(1, dtype=np.uint64)[0] >> np.uint64(1))
        sim, _ = trace_and_render(scene, beams, geom.range_m[idx], mcrt, setup, trace_seed,
                                  np.random.default_rng(ss), 1 if workers > 1 else threads)
        f = sim.features(setup)
        first = sim.echo_times_ns[:, 0]
        h = geom.origin[idx, 2] + geom.direction[idx, 2] * (sim.first_sample_ns + first) * RANGE_PER_NS
        return pd.DataFrame({
            "pulse": idx, "instance": int(k), "n_echoes": sim.n_echoes.astype(int),
            "Apeak": f["Apeak"], "FWHM": f["FWHM"], "E": f["E"], "Npeaks": f["Npeaks"], "H": h,
            "sigma_total": sim.sigma_total,
        })

    frames = [f for _, f in unordered_map(instance, list(np.unique(geom.instance)), workers)]
    out = pd.concat(frames, ignore_index=True).sort_values("pulse").reset_index(drop=True)
    has = out["n_echoes"] > 0
    out.loc[~has, ["Apeak", "FWHM", "E", "Npeaks", "H"]] = np.nan
    return out


def summarise(pulses: pd.DataFrame) -> dict:
    """Mean Apeak and its standard error over pulses with an echo, and companions."""
    a = pulses["Apeak"].to_numpy(float)
    a = a[np.isfinite(a)]
    n = a.size
    row = {"n_pulses": int(len(pulses)), "n_echo": int(n),
           "mean_apeak": float(a.mean()) if n else np.nan,
           "sd_apeak": float(a.std(ddof=1)) if n > 1 else np.nan}
    row["se_apeak"] = row["sd_apeak"] / np.sqrt(n) if n > 1 else np.nan
    for f in ("E", "FWHM", "H"):
        v = pulses[f].to_numpy(float)
        v = v[np.isfinite(v)]
        row[f"mean_{f}"] = float(v.mean()) if v.size else np.nan
    return row


@dataclass(frozen=True)
class SensitivitySummary:
    table: Path
    figure: Path
    pulses_table: Path
    n_settings: int
    pulses: int
    source: str


def run(out_dir, cfg: dict, system_path=None, calibration_path=None, progress: bool = True,
        threads: int | None = None, scene_builder=None) -> SensitivitySummary:
    """The ``sensitivity`` stage: writes sensitivity.csv, sensitivity_baseline.csv,
    sensitivity_pulses.parquet (one row per simulated pulse) and fig8.png.

    sensitivity.csv columns: parameter, value, n_pulses, n_echo, mean_apeak, sd_apeak,
    se_apeak, mean_E, mean_FWHM, mean_H (DN, DN, ns, m), one row per swept setting;
    sensitivity_baseline.csv: the same columns (no value) for the species model as is.
    """

    out_dir = Path(out_dir)
    s = cfg["sensitivity"]
    ref = reference_sensor(cfg, system_path, calibration_path, float(s["range_m"]))
    setup = SensorSetup.from_config(cfg, ref.system, ref.noise_mean, ref.noise_sd, float(s["sampling_ns"]))
    mcrt = MCRTSetup.from_config(cfg, n_rays=s["n_rays"])
    geom = geometry(cfg)
    todo = settings(cfg)
    if progress:
        from tqdm import tqdm

        todo = tqdm(todo, desc="sensitivity", unit="setting")
    rows, per_pulse = [], []
    for param, value, kwargs in todo:
        p = simulate_setting(kwargs, geom, setup, mcrt, cfg, threads, scene_builder)
        rows.append({"parameter": param, "value": value, **summarise(p)})
        per_pulse.append(p.assign(parameter=param, value=value))
    table = pd.DataFrame(rows)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {"csv": out_dir / "sensitivity.csv", "base": out_dir / "sensitivity_baseline.csv",
             "pq": out_dir / "sensitivity_pulses.parquet", "png": out_dir / "fig8.png"}
    with atomic_path(paths["csv"]) as tmp:
        table[table["parameter"] != "baseline"].to_csv(tmp, index=False, float_format="%.6g")
    with atomic_path(paths["base"]) as tmp:
        table[table["parameter"] == "baseline"].drop(columns="value").to_csv(tmp, index=False, float_format="%.6g")
    write_table(pa.Table.from_pandas(pd.concat(per_pulse, ignore_index=True), preserve_index=False), paths["pq"])
    plots.fig8_sensitivity(table, paths["png"], source=ref.source)
    return SensitivitySummary(paths["csv"], paths["png"], paths["pq"], len(table), int(s["pulses"]), ref.source)


@click.command("sensitivity")
@reference_sensor_options("sensitivity.csv, fig8.png")
def sensitivity(system, calibration, out, cfg):
    """Sensitivity of simulated birch Apeak to leaf angle, rho, tau and leaf area (docs/method.md §(i2))."""

    r = run(out, cfg, system_path=system, calibration_path=calibration)
    click.echo(f"sensitivity: {r.n_settings} settings x {r.pulses} pulses -> {r.table}, {r.figure}")
