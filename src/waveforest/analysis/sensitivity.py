"""Sensitivity of simulated birch Apeak to vegetation parameters (docs/method.md §(i2), Fig. 8).

A birch crown of ``sensitivity.height_m`` (3 m) without ground, seen at nadir from
``range_m`` (1200 m) with the reference sensor (S(t) of 2010_12_1 or its Gaussian stand-in,
:mod:`waveforest.sensor.reference`), 1-ns sampling, footprint = divergence x range (0.15 mrad
-> 0.18 m); the sensor XY jittered uniformly within +-``xy_jitter_m`` (0.30 m) of the stem. One
parameter at a time is swept: mean leaf inclination angle (``build_scene(mean_leaf_angle=...)``),
leaf rho, leaf tau, and the scale on each leaf's area; plus the baseline (the species model as
is: spherical LAD, rho 0.47, tau 0.50, scale 1).

Per setting: ``pulses`` pulses spread evenly over ``instances`` birch instances. Common random
numbers: instance k has the same seed (structure), the same beam positions and the same MCRT
and noise streams in every setting, so the curves show the parameter's effect with little
Monte Carlo noise between neighbouring values. Output per setting: mean Apeak of the pulses
with a CFD echo and its standard error (SD / sqrt(n)); pulses without an echo (the beam
missed the crown: no ground) are counted but have no Apeak.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from waveforest.constants import RANGE_PER_NS
from waveforest.mcrt import Beams
from waveforest.mcrt.threads import default_threads
from waveforest.model.forward import MCRTSetup, SensorSettings, SensorSetup, trace_and_render
from waveforest.rng import hashed_generator, hashed_seed63
from waveforest.sensor.reference import ReferenceSensor, ReferenceSystem
from waveforest.vegetation import build_scene
from waveforest.workers import unordered_map

PARAMETERS = ("mean_leaf_angle_deg", "leaf_rho", "leaf_tau", "leaf_area_scale")
"""Swept parameters (config keys of ``sensitivity``) in the order of Fig. 8."""

_BUILD_KWARG = {"mean_leaf_angle_deg": "mean_leaf_angle", "leaf_rho": "leaf_rho", "leaf_tau": "leaf_tau",
                "leaf_area_scale": "leaf_area_scale"}


@dataclass(frozen=True)
class SensitivitySettings:
    """The study (built by :func:`waveforest.settings.sensitivity_settings`): ``pulses`` (int) per
    setting, spread evenly over ``instances`` (int) birch instances; ``seed`` (int) is the master
    seed of every random number of it.

    Attributes
    ----------
    height_m, range_m, xy_jitter_m : float, m
        Birch height; sensor range (nadir); half-width of the sensor's uniform XY jitter.
    divergence_mrad : float, mrad
        Beam divergence (footprint = divergence x range).
    sampling_ns : float, ns
        Sampling interval of the rendered waveforms.
    sweeps : tuple of (parameter, tuple of float)
        The swept values of each of :data:`PARAMETERS`, in that order.
    lai_jitter : float
        Relative SD of the instances' leaf area.
    reference : ReferenceSystem
        The configured reference sensor (Gaussian S(t) when no calibration is given).
    mcrt : MCRTSetup
    sensor : SensorSettings
        The sensor model, completed by the reference S(t), noise and :attr:`sampling_ns`.
    """

    seed: int
    pulses: int
    instances: int
    height_m: float
    range_m: float
    xy_jitter_m: float
    divergence_mrad: float
    sampling_ns: float
    sweeps: tuple[tuple[str, tuple[float, ...]], ...]
    lai_jitter: float
    reference: ReferenceSystem
    mcrt: MCRTSetup
    sensor: SensorSettings


@dataclass(frozen=True)
class SensitivityResult:
    """``table``: one row per setting (baseline first): parameter, value (NaN for the baseline) and
    the columns of :func:`summarise`; ``pulses``: the rows of :func:`simulate_setting` of every
    setting, with its parameter and value."""

    table: pd.DataFrame
    pulses: pd.DataFrame


def sweep(st: SensitivitySettings) -> list[tuple[str, float, dict]]:
    """(parameter, value, build_scene keyword arguments) of every setting, baseline first."""
    out = [("baseline", np.nan, {})]
    for p, values in st.sweeps:
        for v in values:
            out.append((p, float(v), {_BUILD_KWARG[p]: float(v)}))
    return out


@dataclass(frozen=True)
class Geometry:
    """Nadir beams of the study: one per pulse, instance index and sensor offset."""

    instance: np.ndarray  # (n,) int64
    origin: np.ndarray  # (n, 3) float64, m (scene coordinates, ground level z = 0)
    direction: np.ndarray  # (n, 3)
    range_m: np.ndarray  # (n,)


def geometry(st: SensitivitySettings) -> Geometry:
    """The pulses' beams (the same in every setting)."""
    n, k = st.pulses, st.instances
    rng = hashed_generator(st.seed, "sensitivity", "geometry")
    jitter = rng.uniform(-st.xy_jitter_m, st.xy_jitter_m, (n, 2))
    r = st.range_m
    origin = np.column_stack([jitter, np.full(n, r)])
    direction = np.tile([0.0, 0.0, -1.0], (n, 1))
    return Geometry(np.arange(n) % k, origin, direction, np.full(n, r))


def simulate_setting(build_kwargs: dict, geom: Geometry, setup: SensorSetup, st: SensitivitySettings,
                     threads: int | None = None, scene_builder=None) -> pd.DataFrame:
    """Simulate every pulse of one setting; one row per pulse (instance, Apeak, FWHM, E, Npeaks, H).

    The instances are shared over ``threads`` worker threads (:func:`waveforest.workers.unordered_map`);
    the rows do not depend on it.

    ``scene_builder``: ``f(species, height, seed, **kwargs) -> Scene`` (default
    :func:`waveforest.vegetation.build_scene`).
    """
    if scene_builder is None:
        scene_builder = build_scene

    seed = st.seed
    workers = threads if threads is not None else default_threads()

    def instance(k):
        idx = np.flatnonzero(geom.instance == k)
        scene = scene_builder("birch", st.height_m, hashed_seed63(seed, "sensitivity", "scene", int(k)),
                              ground=False, lai_jitter=st.lai_jitter, **build_kwargs)
        beams = Beams.from_divergence(geom.origin[idx], geom.direction[idx], st.divergence_mrad, geom.range_m[idx])
        parts = (seed, "sensitivity", "pulses", int(k))
        trace_seed = hashed_seed63(*parts)
        sim, _ = trace_and_render(scene, beams, geom.range_m[idx], st.mcrt, setup, trace_seed,
                                  hashed_generator(*parts), 1 if workers > 1 else threads)
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
    """Mean Apeak and its standard error over pulses with an echo, and companions.

    Keys: n_pulses, n_echo, mean_apeak, sd_apeak, se_apeak (DN), mean_E (DN ns), mean_FWHM (ns),
    mean_H (m).
    """
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


def run_sensitivity(st: SensitivitySettings, ref: ReferenceSensor, progress: bool = True,
                    threads: int | None = None, scene_builder=None) -> SensitivityResult:
    """Simulate and summarise every setting of :func:`sweep` with the reference sensor ``ref``
    (the same :func:`geometry` in each); ``progress`` shows a tqdm bar."""
    setup = st.sensor.setup(ref.system, ref.noise_mean, ref.noise_sd, st.sampling_ns)
    geom = geometry(st)
    todo = sweep(st)
    if progress:
        from tqdm import tqdm

        todo = tqdm(todo, desc="sensitivity", unit="setting")
    rows, per_pulse = [], []
    for param, value, kwargs in todo:
        p = simulate_setting(kwargs, geom, setup, st, threads, scene_builder)
        rows.append({"parameter": param, "value": value, **summarise(p)})
        per_pulse.append(p.assign(parameter=param, value=value))
    return SensitivityResult(pd.DataFrame(rows), pd.concat(per_pulse, ignore_index=True))
