"""Sensor parameters vs simulated three-species classification (docs/method.md §(i3), Fig. 9).

Birch, raspberry and fireweed (the keys of ``sensor_study.heights_m``), ``instances``
vegetation instances per species with heights uniform in the species' range (Fig. 6 field
heights), ground included. ``pulses`` pulses per species: sensor at ``range_m`` (1200 m)
above the ground, scan zenith uniform in [0, 15] deg, azimuth uniform, aimed at a point
uniform in a disc of ``aim_radius_m`` around the plant at half its height. Defaults of
2010_12_1: the reference S(t) (:mod:`waveforest.sensor.reference`), 1-ns sampling, 0.15 mrad.
One parameter at a time:

* beam divergence (footprint = divergence x R): each value is traced anew;
* emitted pulse width at constant pulse energy: S(t) stretched in time by w/w0 and scaled by
  w0/w (``SystemWaveform.stretched``), CFD delay and dead time following the width;
* sampling interval;

pulse width and sampling do not change sigma(t), so they reuse the sigma of the default
divergence (common random numbers: the same plants, beams and rays in every setting).

Per setting: first-echo Apeak, FWHM and E of every pulse with an echo (birch: first echo at
least ``min_echo_h_m`` above the ground, the tree rule of select), then LDA (class-frequency
priors) at two levels: single pulses, and means of ``group_size`` consecutive pulses of one
instance (a plant seen by several pulses, as a field sample is). Accuracy by resubstitution
(training = validation, the paper's scheme) and by cross-validation with folds that never
split an instance.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np
import pandas as pd

from waveforest.constants import RANGE_PER_NS
from waveforest.mcrt import Beams, prepare, trace
from waveforest.mcrt.threads import default_threads
from waveforest.model.forward import MCRTSetup, SensorSettings, SensorSetup, render_sigma
from waveforest.rng import hashed_generator, hashed_seed63, stable_hash
from waveforest.sensor.reference import ReferenceSensor, ReferenceSystem
from waveforest.stats import lda
from waveforest.vegetation import build_scene
from waveforest.workers import unordered_map

FEATURES = ("Apeak", "FWHM", "E")
"""Features of the LDA (docs/method.md §(i3))."""

LEVELS = ("1-pulse", "multi-pulse")


@dataclass(frozen=True)
class SensorStudySettings:
    """The study (built by :func:`waveforest.settings.sensor_study_settings`); ``seed`` (int) is the
    master seed of every random number of it.

    Attributes
    ----------
    pulses, instances : int
        Pulses per species, over at most this many instances (see :func:`instances_of`).
    heights_m : mapping species -> (lo, hi), m
        The studied species, in order, and the range of their instances' heights.
    range_m : float, m
        Sensor altitude above the ground.
    max_scan_zenith_deg : float, deg
    aim_radius_m : float, m
        Radius of the disc around the plant that the beams aim at.
    min_echo_h_m : mapping species -> float, m
        Lowest first-echo height kept, for the species that have one.
    divergence_mrad, sampling_ns : float
        The default divergence (mrad) and sampling interval (ns).
    divergences_mrad, pulse_widths_ns, samplings_ns : tuple of float
        The swept values.
    group_size : int
        Consecutive pulses of one instance averaged at the multi-pulse level.
    cv_folds : int
    ground_rho, lai_jitter : float
        Ground reflectance and relative SD of the instances' leaf area.
    reference : ReferenceSystem
        The configured reference sensor (Gaussian S(t) when no calibration is given).
    mcrt : MCRTSetup
    sensor : SensorSettings
        The sensor model, completed by the reference S(t), noise and the sampling.
    """

    seed: int
    pulses: int
    instances: int
    heights_m: Mapping[str, tuple[float, float]]
    range_m: float
    max_scan_zenith_deg: float
    aim_radius_m: float
    min_echo_h_m: Mapping[str, float]
    divergence_mrad: float
    sampling_ns: float
    divergences_mrad: tuple[float, ...]
    pulse_widths_ns: tuple[float, ...]
    samplings_ns: tuple[float, ...]
    group_size: int
    cv_folds: int
    ground_rho: float
    lai_jitter: float
    reference: ReferenceSystem
    mcrt: MCRTSetup
    sensor: SensorSettings


@dataclass(frozen=True)
class SensorStudyResult:
    """``table``: parameter, value, is_default and the rows of :func:`classify`; ``features``:
    parameter, value, species, n, mean and SD of each of :data:`FEATURES`; ``n_settings``;
    ``n_pulses``: pulses classified over all settings."""

    table: pd.DataFrame
    features: pd.DataFrame
    n_settings: int
    n_pulses: int


@dataclass(frozen=True)
class SpeciesPulses:
    """The fixed geometry of one species' pulses.

    Attributes
    ----------
    species : str
    heights : (k,) float64, m, of the instances
    instance : (n,) int64, instance of each pulse (pulses sorted by instance)
    origin : (n, 3) float64, m, scene coordinates (ground z = 0, plant at the origin)
    direction : (n, 3) float64
    range_m : (n,) float64, range to the ground plane along the beam (R of Eq. 7), m
    """

    species: str
    heights: np.ndarray
    instance: np.ndarray
    origin: np.ndarray
    direction: np.ndarray
    range_m: np.ndarray


def instances_of(st: SensorStudySettings) -> int:
    """Instances per species: ``instances``, but at most pulses // group_size so that every
    instance has at least one multi-pulse group."""
    return max(1, min(st.instances, st.pulses // st.group_size))


def species_pulses(st: SensorStudySettings, species: str) -> SpeciesPulses:
    """Draw the instances' heights and the pulses' beams of one species (seeded)."""
    lo, hi = st.heights_m[species]
    n = st.pulses
    k = instances_of(st)
    rng = hashed_generator(st.seed, "sensor_study", species, "geometry")
    heights = rng.uniform(lo, hi, k)
    instance = np.sort(np.arange(n) % k)
    zen = np.radians(rng.uniform(0.0, st.max_scan_zenith_deg, n))
    az = rng.uniform(0.0, 2 * np.pi, n)
    direction = np.column_stack([np.sin(zen) * np.cos(az), np.sin(zen) * np.sin(az), -np.cos(zen)])
    rad = st.aim_radius_m * np.sqrt(rng.random(n))
    phi = rng.uniform(0.0, 2 * np.pi, n)
    target = np.column_stack([rad * np.cos(phi), rad * np.sin(phi), 0.5 * heights[instance]])
    altitude = st.range_m
    along = (altitude - target[:, 2]) / np.cos(zen)  # target -> sensor distance
    origin = target - direction * along[:, None]
    return SpeciesPulses(species, heights, instance, origin, direction, altitude / np.cos(zen))


def trace_species(sp: SpeciesPulses, divergences, st: SensorStudySettings, threads=None,
                  scene_builder=None) -> dict:
    """sigma(t) of every pulse of a species at each beam divergence (mrad), traced with ``st.mcrt``.

    Each instance is built and prepared once and traced at every divergence with the same
    MCRT seed (common random numbers across the divergences). The instances are shared over
    ``threads`` worker threads (:func:`waveforest.workers.unordered_map`); the result does not
    depend on it.

    ``scene_builder``: ``f(species, height, seed, **kwargs) -> Scene`` (default
    :func:`waveforest.vegetation.build_scene`).

    Returns
    -------
    dict divergence -> (sigma (n, n_bins) float64, t0_ns (n,) float64, sigma_total (n,) float64)
    """
    if scene_builder is None:
        scene_builder = build_scene
    seed = st.seed
    n = len(sp.instance)
    workers = threads if threads is not None else default_threads()

    def instance(k):
        idx = np.flatnonzero(sp.instance == k)
        scene_seed = hashed_seed63(seed, "sensor_study", sp.species, "scene", int(k))
        scene = scene_builder(sp.species, float(sp.heights[k]), scene_seed,
                              ground_rho=st.ground_rho, lai_jitter=st.lai_jitter)
        prepared = prepare(scene)
        return idx, {div: trace(prepared, Beams.from_divergence(sp.origin[idx], sp.direction[idx], float(div),
                                                                sp.range_m[idx]),
                                seed=hashed_seed63(seed, "sensor_study", sp.species, "mcrt", int(k)),
                                threads=1 if workers > 1 else threads, **st.mcrt.kwargs())
                     for div in divergences}

    out: dict = {}
    for _, (idx, by_div) in unordered_map(instance, list(np.unique(sp.instance)), workers):
        for div, res in by_div.items():
            if div not in out:
                out[div] = (np.zeros((n, res.sigma.shape[1])), np.zeros(n), np.zeros(n))
            sigma, t0, total = out[div]
            sigma[idx], t0[idx], total[idx] = res.sigma, res.t0_ns, res.total
    return out


def features_of(sp: SpeciesPulses, sigma, t0, total, setup: SensorSetup, rng, min_h: float | None) -> pd.DataFrame:
    """Render, detect and compute first-echo features; one row per pulse kept."""
    sim = render_sigma(sigma, t0, sp.range_m, setup, rng, sigma_total=total)
    f = sim.features(setup)
    first = sim.echo_times_ns[:, 0]
    h = sp.origin[:, 2] + sp.direction[:, 2] * (sim.first_sample_ns + first) * RANGE_PER_NS
    df = pd.DataFrame({"species": sp.species, "instance": sp.instance, "pulse": np.arange(len(sp.instance)),
                       "n_echoes": sim.n_echoes.astype(int), "H": h,
                       **{k: np.asarray(f[k], dtype=float) for k in FEATURES}})
    keep = (df["n_echoes"] > 0) & np.all(np.isfinite(df[list(FEATURES)].to_numpy()), axis=1)
    if min_h is not None:
        keep &= df["H"] >= min_h
    return df[keep]


def classify(df: pd.DataFrame, st: SensorStudySettings, labels: list) -> list[dict]:
    """LDA of one setting: rows (level, scheme, accuracy, kappa, n) for both levels and both
    validation schemes."""
    x = df[list(FEATURES)].to_numpy(float)
    y = df["species"].astype(str).to_numpy(object)
    units = (df["species"].astype(str) + "#" + df["instance"].astype(str)).to_numpy(object)
    out = []
    folds, seed = st.cv_folds, st.seed
    present = [c for c in labels if c in set(y)]
    blocks = {}
    if len(present) >= 2:
        blocks["1-pulse"] = lda.evaluate(x, y, units, present, folds, seed)
        xm, ym, um = lda.consecutive_means(x, y, df["pulse"].to_numpy(), units, st.group_size)
        if len(set(ym)) >= 2:
            blocks["multi-pulse"] = lda.evaluate(xm, ym, um, [c for c in present if c in set(ym)], folds, seed)
    for level in LEVELS:
        for scheme in ("resubstitution", "cross_validated"):
            sc = (blocks.get(level) or {}).get(scheme)
            if sc is None:  # too few items for this level or scheme: no row rather than NaN
                continue
            out.append({"level": level if level == "1-pulse" else f"{st.group_size}-pulse",
                        "scheme": scheme, "accuracy": sc["accuracy"], "kappa": sc["kappa"], "n": sc["n"]})
    return out


def divergences(st: SensorStudySettings) -> list[float]:
    """The traced divergences (mrad): the swept ones and the default, sorted."""
    return sorted(set(st.divergences_mrad) | {st.divergence_mrad})


def sweep(st: SensorStudySettings) -> list[tuple[str, float]]:
    """(parameter, value) of every setting: divergences, then pulse widths, then samplings."""
    return ([("divergence_mrad", v) for v in divergences(st)]
            + [("pulse_width_ns", v) for v in st.pulse_widths_ns]
            + [("sampling_ns", v) for v in st.samplings_ns])


def run_sensor_study(st: SensorStudySettings, ref: ReferenceSensor, progress: bool = True,
                     threads: int | None = None, scene_builder=None) -> SensorStudyResult:
    """Trace each species once per divergence, then render, detect and classify every setting of
    :func:`sweep` with the reference sensor ``ref``; ``progress`` shows a tqdm bar."""
    species = list(st.heights_m)
    base = st.sensor.setup(ref.system, ref.noise_mean, ref.noise_sd, st.sampling_ns)
    pulses = {sp: species_pulses(st, sp) for sp in species}
    default_div = st.divergence_mrad
    default_w = float(ref.system.fwhm_ns)
    settings = sweep(st)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(species) + len(settings), desc="sensor-study", unit="step")
    sigmas: dict = {}
    for sp in species:
        for v, traced in trace_species(pulses[sp], divergences(st), st, threads, scene_builder).items():
            sigmas[(v, sp)] = traced
        if bar is not None:
            bar.update(1)
    rows, feat_rows = [], []
    n_total = 0
    for param, value in settings:
        div = value if param == "divergence_mrad" else default_div
        setup = base
        if param == "pulse_width_ns":
            setup = base.with_system(ref.system.stretched(value), st.sensor.cfd)
        elif param == "sampling_ns":
            setup = replace(base, sampling_ns=value)
        frames = []
        for sp in species:
            rng = hashed_generator(st.seed, "sensor_study", "render", param, stable_hash(repr(value)), sp)
            sigma, t0, total = sigmas[(div, sp)]
            frames.append(features_of(pulses[sp], sigma, t0, total, setup, rng, st.min_echo_h_m.get(sp)))
        df = pd.concat(frames, ignore_index=True)
        n_total += len(df)
        is_default = {"divergence_mrad": value == default_div, "sampling_ns": value == st.sampling_ns,
                      "pulse_width_ns": bool(np.isclose(value, default_w, rtol=0.02))}[param]
        for r in classify(df, st, species):
            rows.append({"parameter": param, "value": value, "is_default": is_default, **r})
        for sp, g in df.groupby("species", sort=False):
            fr = {"parameter": param, "value": value, "species": sp, "n": len(g)}
            for f in FEATURES:
                fr[f"mean_{f}"] = float(g[f].mean())
                fr[f"sd_{f}"] = float(g[f].std(ddof=1)) if len(g) > 1 else np.nan
            feat_rows.append(fr)
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    return SensorStudyResult(pd.DataFrame(rows), pd.DataFrame(feat_rows), len(settings), n_total)
