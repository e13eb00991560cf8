"""Sensor parameters vs simulated three-species classification (docs/method.md §(i3), Fig. 9).

Birch, raspberry and fireweed (the keys of ``sensor_study.heights_m``), ``instances``
vegetation instances per species with heights uniform in the species' range (Fig. 6 field
heights), ground included. ``pulses`` pulses per species: sensor at ``range_m`` (1200 m)
above the ground, scan zenith uniform in [0, 15] deg, azimuth uniform, aimed at a point
uniform in a disc of ``aim_radius_m`` around the plant at half its height. Defaults of
2010_12_1: the reference S(t) (:mod:`.reference`), 1-ns sampling, 0.15 mrad. One parameter
at a time:

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

from dataclasses import dataclass, replace
from pathlib import Path

import click
import numpy as np
import pandas as pd

from waveforest.atomic import atomic_path
from waveforest.cliutil import reference_sensor_options
from waveforest.constants import RANGE_PER_NS
from waveforest.mcrt import Beams, prepare, trace
from waveforest.mcrt.threads import default_threads
from waveforest.model.forward import MCRTSetup, SensorSetup, render_sigma
from waveforest.report import plots
from waveforest.rng import hashed_seed63, hashed_sequence, stable_hash
from waveforest.sensor.reference import reference_sensor
from waveforest.stats import lda
from waveforest.vegetation import build_scene
from waveforest.workers import unordered_map

FEATURES = ("Apeak", "FWHM", "E")
"""Features of the LDA (docs/method.md §(i3))."""

LEVELS = ("1-pulse", "multi-pulse")


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


def instances_of(cfg: dict) -> int:
    """Instances per species: ``instances``, but at most pulses // group_size so that every
    instance has at least one multi-pulse group."""
    s = cfg["sensor_study"]
    return max(1, min(int(s["instances"]), int(s["pulses"]) // int(s["group_size"])))


def species_pulses(cfg: dict, species: str) -> SpeciesPulses:
    """Draw the instances' heights and the pulses' beams of one species (seeded)."""
    s = cfg["sensor_study"]
    seed = int(cfg["seed"])
    lo, hi = (float(v) for v in s["heights_m"][species])
    n = int(s["pulses"])
    k = instances_of(cfg)
    rng = np.random.default_rng(hashed_sequence(seed, "sensor_study", species, "geometry"))
    heights = rng.uniform(lo, hi, k)
    instance = np.sort(np.arange(n) % k)
    zen = np.radians(rng.uniform(0.0, float(s["max_scan_zenith_deg"]), n))
    az = rng.uniform(0.0, 2 * np.pi, n)
    direction = np.column_stack([np.sin(zen) * np.cos(az), np.sin(zen) * np.sin(az), -np.cos(zen)])
    rad = float(s["aim_radius_m"]) * np.sqrt(rng.random(n))
    phi = rng.uniform(0.0, 2 * np.pi, n)
    target = np.column_stack([rad * np.cos(phi), rad * np.sin(phi), 0.5 * heights[instance]])
    altitude = float(s["range_m"])
    along = (altitude - target[:, 2]) / np.cos(zen)  # target -> sensor distance
    origin = target - direction * along[:, None]
    return SpeciesPulses(species, heights, instance, origin, direction, altitude / np.cos(zen))


def trace_species(sp: SpeciesPulses, divergences, mcrt: MCRTSetup, cfg: dict, threads=None,
                  scene_builder=None) -> dict:
    """sigma(t) of every pulse of a species at each beam divergence.

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
    seed = int(cfg["seed"])
    veg = cfg["vegetation"]
    n = len(sp.instance)
    workers = threads if threads is not None else default_threads()

    def instance(k):
        idx = np.flatnonzero(sp.instance == k)
        scene_seed = hashed_seed63(seed, "sensor_study", sp.species, "scene", int(k))
        scene = scene_builder(sp.species, float(sp.heights[k]), scene_seed,
                              ground_rho=float(veg["ground_rho"]), lai_jitter=float(veg["lai_jitter"]))
        prepared = prepare(scene)
        return idx, {div: trace(prepared, Beams.from_divergence(sp.origin[idx], sp.direction[idx], float(div),
                                                                sp.range_m[idx]),
                                seed=hashed_seed63(seed, "sensor_study", sp.species, "mcrt", int(k)),
                                threads=1 if workers > 1 else threads, **mcrt.kwargs())
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


def classify(df: pd.DataFrame, cfg: dict, labels: list) -> list[dict]:
    """LDA of one setting: rows for both levels and both validation schemes."""
    s = cfg["sensor_study"]
    x = df[list(FEATURES)].to_numpy(float)
    y = df["species"].astype(str).to_numpy(object)
    units = (df["species"].astype(str) + "#" + df["instance"].astype(str)).to_numpy(object)
    out = []
    folds, seed = int(s["cv_folds"]), int(cfg["seed"])
    present = [c for c in labels if c in set(y)]
    blocks = {}
    if len(present) >= 2:
        blocks["1-pulse"] = lda.evaluate(x, y, units, present, folds, seed)
        xm, ym, um = lda.consecutive_means(x, y, df["pulse"].to_numpy(), units, int(s["group_size"]))
        if len(set(ym)) >= 2:
            blocks["multi-pulse"] = lda.evaluate(xm, ym, um, [c for c in present if c in set(ym)], folds, seed)
    for level in LEVELS:
        for scheme in ("resubstitution", "cross_validated"):
            sc = (blocks.get(level) or {}).get(scheme)
            if sc is None:  # too few items for this level or scheme: no row rather than NaN
                continue
            out.append({"level": level if level == "1-pulse" else f"{int(s['group_size'])}-pulse",
                        "scheme": scheme, "accuracy": sc["accuracy"], "kappa": sc["kappa"], "n": sc["n"]})
    return out


@dataclass(frozen=True)
class SensorStudySummary:
    table: Path
    figure: Path
    features_table: Path
    n_settings: int
    n_pulses: int
    source: str


def run(out_dir, cfg: dict, system_path=None, calibration_path=None, progress: bool = True,
        threads: int | None = None, scene_builder=None) -> SensorStudySummary:
    """The ``sensor-study`` stage: writes sensor_study.csv, sensor_study_features.csv, fig9.png.

    sensor_study.csv: parameter, value, is_default, level (1-pulse / 5-pulse), scheme
    (resubstitution / cross_validated), accuracy, kappa, n (items classified).
    sensor_study_features.csv: parameter, value, species, n, mean and SD of Apeak, FWHM, E.
    """
    out_dir = Path(out_dir)
    s = cfg["sensor_study"]
    species = list(s["heights_m"])
    ref = reference_sensor(cfg, system_path, calibration_path, float(s["range_m"]))
    base = SensorSetup.from_config(cfg, ref.system, ref.noise_mean, ref.noise_sd, float(s["sampling_ns"]))
    mcrt = MCRTSetup.from_config(cfg, n_rays=s["n_rays"])
    min_h = {k: float(v) for k, v in s["min_echo_h_m"].items()}
    pulses = {sp: species_pulses(cfg, sp) for sp in species}
    default_div = float(s["divergence_mrad"])
    default_w = float(ref.system.fwhm_ns)
    divergences = sorted(set(float(v) for v in s["divergences_mrad"]) | {default_div})
    settings = ([("divergence_mrad", v) for v in divergences]
                + [("pulse_width_ns", float(v)) for v in s["pulse_widths_ns"]]
                + [("sampling_ns", float(v)) for v in s["samplings_ns"]])
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(species) + len(settings), desc="sensor-study", unit="step")
    sigmas: dict = {}
    for sp in species:
        for v, traced in trace_species(pulses[sp], divergences, mcrt, cfg, threads, scene_builder).items():
            sigmas[(v, sp)] = traced
        if bar is not None:
            bar.update(1)
    rows, feat_rows = [], []
    n_total = 0
    seed = int(cfg["seed"])
    for param, value in settings:
        div = value if param == "divergence_mrad" else default_div
        setup = base
        if param == "pulse_width_ns":
            setup = base.with_system(ref.system.stretched(value), cfg)
        elif param == "sampling_ns":
            setup = replace(base, sampling_ns=value)
        frames = []
        for sp in species:
            rng = np.random.default_rng(hashed_sequence(seed, "sensor_study", "render", param,
                                                      stable_hash(repr(value)), sp))
            sigma, t0, total = sigmas[(div, sp)]
            frames.append(features_of(pulses[sp], sigma, t0, total, setup, rng, min_h.get(sp)))
        df = pd.concat(frames, ignore_index=True)
        n_total += len(df)
        is_default = {"divergence_mrad": value == default_div, "sampling_ns": value == float(s["sampling_ns"]),
                      "pulse_width_ns": bool(np.isclose(value, default_w, rtol=0.02))}[param]
        for r in classify(df, cfg, species):
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
    table = pd.DataFrame(rows)
    feats = pd.DataFrame(feat_rows)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {"csv": out_dir / "sensor_study.csv", "feat": out_dir / "sensor_study_features.csv",
             "png": out_dir / "fig9.png"}
    with atomic_path(paths["csv"]) as tmp:
        table.to_csv(tmp, index=False, float_format="%.6g")
    with atomic_path(paths["feat"]) as tmp:
        feats.to_csv(tmp, index=False, float_format="%.6g")
    plots.fig9_sensor(table, paths["png"])
    return SensorStudySummary(paths["csv"], paths["png"], paths["feat"], len(settings), n_total, ref.source)


@click.command("sensor-study")
@reference_sensor_options("sensor_study.csv, fig9.png")
def sensor_study(system, calibration, out, cfg):
    """Divergence, pulse width and sampling vs three-species LDA accuracy (docs/method.md §(i3))."""

    r = run(out, cfg, system_path=system, calibration_path=calibration)
    click.echo(f"sensor-study: {r.n_settings} settings, {r.n_pulses} simulated pulses -> {r.table}, {r.figure}")
