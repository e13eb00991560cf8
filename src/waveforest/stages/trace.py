"""The ``trace`` stage: one scene, one pulse -> sigma(t) table (Parquet or CSV) and a plot.

The scene is a PLY file whose faces carry ``rho``, ``tau`` and ``kind``, or a vegetation
instance built by :func:`waveforest.vegetation.build_scene` from a species and a height.
"""

from __future__ import annotations

import json
import time
import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import click
import numpy as np
import pandas as pd
import pyarrow as pa

from waveforest.atomic import atomic_path
from waveforest.cliutil import (
    stage_options,
    warnings_to_stderr,
)
from waveforest.constants import RANGE_PER_NS
from waveforest.effects import CATALOGUE, parse_effects
from waveforest.errors import WaveforestError
from waveforest.io.pulses import write_table
from waveforest.mcrt.beams import BeamSpec
from waveforest.mcrt.tracer import TraceResult
from waveforest.mcrt.tracer import trace as trace_pulses
from waveforest.model.forward import MCRTSetup, noise_free_waveform
from waveforest.plotting import pyplot, save_png
from waveforest.scene import Scene, read_ply
from waveforest.sensor.reference import reference_sensor
from waveforest.settings import mcrt_setup, reference_system

TABLE_SUFFIXES = (".parquet", ".csv")

PLOT_FRACTION = 0.999
"""The plot of sigma(t) spans the bins holding this fraction of the binned sigma."""


@dataclass(frozen=True)
class SceneSpec:
    """The scene to trace: a PLY file (``path``), or a vegetation instance of ``species`` and
    ``height_m`` built with ``ground_rho`` and ``lai_jitter`` (config section ``vegetation``)."""

    path: str | Path | None
    species: str | None
    height_m: float | None
    ground_rho: float
    lai_jitter: float
    plant_seed: int | None = None

    def describe(self) -> str:
        """The scene as the output's metadata names it."""
        return str(self.path) if self.path is not None else f"{self.species} h={self.height_m}"

    def load(self, seed: int) -> Scene:
        """Read the PLY file, or build the instance with ``plant_seed`` (None: ``seed``)."""
        if self.path is None and self.species is None:
            raise WaveforestError("trace: give a scene PLY file or --species (with --height)")
        if self.path is not None and self.species is not None:
            raise WaveforestError("trace: give a scene PLY file or --species, not both")
        if self.path is not None:
            if self.height_m is not None or self.plant_seed is not None:
                raise WaveforestError("trace: --height and --plant-seed build a --species instance, not a PLY file")
            return read_ply(self.path)
        if self.height_m is None or not self.height_m > 0:
            raise WaveforestError("trace: --species needs --height (m, > 0)")
        from waveforest.vegetation import build_scene  # not imported to trace a PLY file

        plant = seed if self.plant_seed is None else self.plant_seed
        return build_scene(self.species, float(self.height_m), int(plant), ground_rho=self.ground_rho,
                           lai_jitter=self.lai_jitter)


def mcrt_effects(effects) -> dict[str, float]:
    """The MCRT effects (``specular``, ``hotspot``) from NAME=VALUE strings or a mapping."""
    parsed = parse_effects(effects)
    wrong = [k for k in parsed if CATALOGUE[k].stage != "mcrt"]
    if wrong:
        raise WaveforestError(f"--effect {', '.join(wrong)}: not an MCRT effect (expected specular or hotspot)")
    return parsed


def write_sigma(result: TraceResult, path: str | Path, i: int = 0, metadata: dict | None = None) -> Path:
    """Write sigma(t) of pulse ``i`` (time, range, sigma, sigma per order) as Parquet or CSV."""
    return write_frame(result.frame(i), path, metadata)


def write_frame(df: pd.DataFrame, path: str | Path, metadata: dict | None = None) -> Path:
    """Write ``df`` as Parquet or CSV (the suffix chooses); Parquet carries ``metadata`` (JSON)."""
    path = Path(path)
    if path.suffix.lower() not in TABLE_SUFFIXES:
        raise WaveforestError(f"{path}: expected a .parquet or .csv output file")
    if path.suffix.lower() == ".csv":
        with atomic_path(path) as tmp:
            df.to_csv(tmp, index=False, float_format="%.10g")
        return path
    table = pa.Table.from_pandas(df, preserve_index=False)
    meta = {"waveforest.trace": json.dumps(metadata or {}, default=float)}
    return write_table(table.replace_schema_metadata(meta), path)


def plot_sigma(result: TraceResult, path: str | Path, i: int = 0, title: str = "") -> Path:
    """PNG of sigma(t) of pulse ``i``, total and per scattering order, against range."""
    plt = pyplot()
    sigma = result.sigma[i]
    nz = np.flatnonzero(sigma)
    if nz.size:  # from the first return to 99.9 % of the binned sigma
        cum = np.cumsum(sigma)
        lo, hi = nz[0], int(np.searchsorted(cum, PLOT_FRACTION * cum[-1])) + 1
    else:
        lo, hi = 0, result.n_bins
    pad = max(10, (hi - lo) // 10)
    sl = slice(max(0, lo - pad), min(result.n_bins, hi + pad))
    rng_m = result.bin_ns * np.arange(result.n_bins) * RANGE_PER_NS  # one-way range after bin 0
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(rng_m[sl], sigma[sl] / result.bin_ns, color="k", lw=1.5, label="total")
    if result.sigma_by_order is not None:
        for k in range(result.max_order):
            s = result.sigma_by_order[i, k]
            if np.any(s[sl] > 0):
                ax.plot(rng_m[sl], s[sl] / result.bin_ns, lw=0.8, label=f"order {k + 1}")
    ax.set_xlabel("range after bin 0 (m)")
    ax.set_ylabel("sigma (sr$^{-1}$ ns$^{-1}$ per unit power)")
    ax.set_title(title or f"sigma(t): total {result.total[i]:.4g}, {result.n_rays} rays")
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    return save_png(fig, path, dpi=120)


def run(scene: SceneSpec, beam: BeamSpec, mcrt: MCRTSetup, out: str | Path, *, seed: int, window_ns: float,
        sensor, plot: str | Path | None = None, waveform: str | Path | None = None) -> tuple[TraceResult, dict]:
    """Trace one pulse through one scene and write its sigma(t) (and a plot, and the waveform
    ``sensor`` records).

    Parameters
    ----------
    scene : SceneSpec
    beam : BeamSpec
        The pulse (neither footprint nor divergence: the ALS60's divergence).
    mcrt : MCRTSetup
        Tracer settings and MCRT effects (``specular``, ``hotspot``); with ``tolerance`` set,
        the adaptive ray budget against ``sensor``, else ``mcrt.n_rays`` rays.
    out : path
        ``.parquet`` or ``.csv`` output.
    seed : int
        Seed of the tracer (and of the vegetation instance unless ``scene.plant_seed``).
    window_ns : float
        Length of the sigma(t) window, ns of two-way time.
    sensor : waveforest.sensor.reference.ReferenceSensor
        The sensor of the recorded waveform, its features and the ray budget.
    plot, waveform : path, optional
        PNG of sigma(t) by order; the recorded waveform
        (:func:`waveforest.model.forward.noise_free_waveform`), .parquet or .csv.

    Returns
    -------
    (TraceResult, metadata dict written with the table: rays, the budget's error, features, ...)
    """
    out = Path(out)
    for path in (out, waveform):
        if path is not None and Path(path).suffix.lower() not in TABLE_SUFFIXES:
            raise WaveforestError(f"{path}: expected a .parquet or .csv output file")
    if beam.footprint_m is not None and beam.divergence_mrad is not None:
        raise WaveforestError("trace: give --footprint or --divergence, not both")
    mcrt_effects(mcrt.effects)
    loaded = scene.load(seed)
    try:
        beams = beam.beams()
        budget = mcrt.budget(sensor.system, sensor.noise_sd, beam.range_m)
        result = trace_pulses(loaded, beams, seed=seed, window_ns=window_ns, by_order=True, **mcrt.kwargs(), **budget)
    except ValueError as exc:
        if isinstance(exc, WaveforestError):
            raise
        raise WaveforestError(f"trace: {exc}") from None
    t_ns, v, features = noise_free_waveform(result, sensor.system, sensor.noise_sd, beam.range_m)
    wave = pd.DataFrame({"time_ns": t_ns, "waveform_dn": v})
    meta = {
        "scene": scene.describe(), "plant_seed": scene.plant_seed if scene.plant_seed is not None else seed,
        "sensor_xyz": beams.origin[0].tolist(), "dir_xyz": beams.direction[0].tolist(),
        "footprint_m": float(beams.footprint_m[0]), "range_m": float(beam.range_m),
        "t0_ns": float(result.t0_ns[0]), "bin_ns": result.bin_ns, "n_rays": int(result.rays[0]),
        "tolerance": mcrt.tolerance if budget else None,
        "mc_error_noise_sd": float(result.mc_error[0]), "max_rays": mcrt.max_rays if budget else None,
        "max_order": mcrt.max_order, "seed": seed, "sampler": mcrt.sampler, "roulette": mcrt.roulette,
        "effects": dict(mcrt.effects),
        "order_totals": result.order_totals[0].tolist(), "sigma_dropped": float(result.sigma_dropped[0]),
        "first_hit_counts": result.first_hit_counts[0].tolist(),
        "sensor": sensor.source, "noise_sd_dn": float(sensor.noise_sd), "features": features,
    }
    write_sigma(result, out, 0, meta)
    if waveform is not None:
        write_frame(wave, waveform, meta)
    if plot is not None:
        plot_sigma(result, plot)
    return result, meta


@click.command("trace")
@click.argument("scene", required=False, type=click.Path(exists=True, dir_okay=False))
@click.option("--out", "out", required=True, type=click.Path(dir_okay=False),
              help="Output sigma(t) table, .parquet or .csv (time_ns, range_m, sigma, sigma per order).")
@click.option("--species", default=None, help="Trace a vegetation instance of this species slug instead of SCENE.")
@click.option("--height", type=click.FloatRange(min=0, min_open=True), default=None, help="Height of the vegetation instance, m (with --species).")
@click.option("--plant-seed", type=click.IntRange(min=0), default=None,
              help="Seed of the --species instance (default: --seed): hold the plant while --seed varies the rays.")
@click.option("--range", "range_m", type=click.FloatRange(min=0, min_open=True), default=1200.0, show_default=True,
              help="Sensor distance from the target point, m.")
@click.option("--scan-zenith", type=float, default=0.0, show_default=True, help="Beam zenith angle, degrees.")
@click.option("--azimuth", type=float, default=0.0, show_default=True,
              help="Compass azimuth of the beam's travel, degrees clockwise from north (+y).")
@click.option("--footprint", type=click.FloatRange(min=0), default=None,
              help="1/e footprint diameter of a collimated beam, m (default: --divergence 0.15).")
@click.option("--divergence", type=click.FloatRange(min=0), default=None, help="1/e beam divergence, mrad (diverging beam).")
@click.option("--target-x", type=float, default=0.0, show_default=True, help="Target point x, m (scene coordinates).")
@click.option("--target-y", type=float, default=0.0, show_default=True, help="Target point y, m.")
@click.option("--target-z", type=float, default=0.0, show_default=True, help="Target point z, m.")
@click.option("--rays", type=click.IntRange(min=1), default=None,
              help="A fixed number of rays per pulse (default: the adaptive budget of config mcrt.tolerance, "
                   "or mcrt.n_rays if it is null).")
@click.option("--tolerance", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Adaptive ray budget: trace until the recorded waveform's Monte Carlo SD is this fraction of "
                   "the noise SD of the reference sensor (config sensitivity.reference_system) "
                   "(default: config mcrt.tolerance).")
@click.option("--orders", type=click.IntRange(min=1), default=None, help="Highest scattering order (default: config mcrt.max_order).")
@click.option("--effect", "effects", multiple=True, metavar="NAME=VALUE",
              help="MCRT effect: specular=FRACTION or hotspot=FACTOR (repeatable).")
@click.option("--plot", type=click.Path(dir_okay=False), default=None, help="PNG of sigma(t) by scattering order.")
@click.option("--waveform", type=click.Path(dir_okay=False), default=None,
              help="Also write the noise-free waveform the reference sensor records (time_ns, waveform_dn), "
                   ".parquet or .csv.")
@stage_options
def trace(scene, out, species, height, plant_seed, range_m, scan_zenith, azimuth, footprint, divergence,
          target_x, target_y, target_z, rays, tolerance, orders, effects, plot, waveform, cfg):
    """Trace one LiDAR pulse through SCENE (a PLY whose faces carry rho, tau, kind) -> sigma(t).

    Writes sigma(t) on the fine time grid (config mcrt.bin_ns) with its per-order split,
    and optionally a plot and the recorded waveform. Rays: the adaptive budget of --tolerance
    (config mcrt.tolerance) against the reference sensor (config sensitivity.reference_system),
    or --rays per pulse; the sampler and roulette are config mcrt.sampler and mcrt.roulette
    (random and 0: plain Monte Carlo). Prints the rays used, the budget's estimated error and
    the first-echo features (Apeak, E, FWHM) of the recorded waveform. Example:

      waveforest trace canopy.ply --out sigma.parquet --range 1200 --scan-zenith 10 --plot sigma.png
    """

    veg = cfg["vegetation"]
    mcrt = mcrt_setup(cfg, effects=mcrt_effects(list(effects)))
    if rays is not None and tolerance is not None:
        raise click.UsageError("give --rays or --tolerance, not both")
    if rays is not None:
        mcrt = replace(mcrt, n_rays=rays, tolerance=None)
    if tolerance is not None:
        mcrt = replace(mcrt, tolerance=tolerance)
    if orders is not None:
        mcrt = replace(mcrt, max_order=orders)
    spec = SceneSpec(path=scene, species=species, height_m=height, ground_rho=veg["ground_rho"],
                     lai_jitter=veg["lai_jitter"], plant_seed=plant_seed)
    beam = BeamSpec(target=(target_x, target_y, target_z), range_m=range_m, scan_zenith_deg=scan_zenith,
                    azimuth_deg=azimuth, footprint_m=footprint, divergence_mrad=divergence)
    t = time.perf_counter()
    sensor = reference_sensor(reference_system(cfg), range_m=range_m)
    with warnings_to_stderr():
        res, meta = run(spec, beam, mcrt, out, seed=cfg["seed"], window_ns=cfg["mcrt"]["window_ns"], sensor=sensor,
                        plot=plot, waveform=waveform)
        if res.total[0] == 0:
            warnings.warn(f"the beam met nothing: sigma is 0 (the target ({target_x:g}, {target_y:g}, "
                          f"{target_z:g}) lies outside the scene?)", stacklevel=1)
        if mcrt.tolerance is not None and meta["mc_error_noise_sd"] > mcrt.tolerance:
            warnings.warn(f"the ray budget stopped at mcrt.max_rays ({mcrt.max_rays}) with an estimated error of "
                          f"{meta['mc_error_noise_sd']:.3g} noise SD, above the tolerance {mcrt.tolerance:g}",
                          stacklevel=1)
    dt = time.perf_counter() - t
    o, f = res.order_totals[0], meta["features"]
    budget = (f"adaptive, tolerance {mcrt.tolerance:g}, estimated error {meta['mc_error_noise_sd']:.3g} noise SD"
              if mcrt.tolerance is not None else "fixed")
    click.echo(
        f"wrote {out}: 1 pulse, {res.n_bins} bins of {res.bin_ns:g} ns, sigma {res.total[0]:.5g} "
        f"(order 1 {o[0]:.5g}, dropped {res.sigma_dropped[0]:.3g}), {res.n_rays} rays ({budget}); "
        f"first echo Apeak {f['Apeak']:.4g} DN, E {f['E']:.4g} DN ns, FWHM {f['FWHM']:.4g} ns; {dt:.2f} s"
        + (f"; waveform {waveform}" if waveform else "") + (f"; plot {plot}" if plot else "")
    )
