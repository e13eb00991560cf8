"""The ``trace`` stage: one scene, one pulse -> sigma(t) table (Parquet or CSV) and a plot.

The scene is a PLY file whose faces carry ``rho``, ``tau`` and ``kind``, or a vegetation
instance built by :func:`waveforest.vegetation.build_scene` from a species and a height.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..atomic import atomic_path
from ..constants import RANGE_PER_NS
from ..effects import CATALOGUE, parse_effects
from ..errors import WaveforestError
from ..scene import Scene, read_ply
from .beams import Beams
from .tracer import DEFAULT_WINDOW_NS, TraceResult, trace

DEFAULT_DIVERGENCE_MRAD = 0.15
"""ALS60 1/e beam divergence (METHOD.md a), used when neither footprint nor divergence is given."""

TABLE_SUFFIXES = (".parquet", ".csv")

PLOT_FRACTION = 0.999
"""The plot of sigma(t) spans the bins holding this fraction of the binned sigma."""


def load_scene(scene_path: str | Path | None, species: str | None = None, height: float | None = None,
               seed: int = 0, vegetation_options: dict | None = None) -> Scene:
    """The scene to trace: a PLY file, or a vegetation instance of ``species`` and ``height``."""
    if (scene_path is None) == (species is None):
        raise WaveforestError("trace: give either a scene PLY file or --species (with --height), not both")
    if scene_path is not None:
        return read_ply(scene_path)
    if height is None or not height > 0:
        raise WaveforestError("trace: --species needs --height (m, > 0)")
    try:
        from ..vegetation import build_scene
    except ImportError as exc:  # the vegetation stage is a separate module
        raise WaveforestError(f"trace: --species needs waveforest.vegetation ({exc})") from None
    return build_scene(species, float(height), int(seed), **(vegetation_options or {}))


def mcrt_effects(effects) -> dict[str, float]:
    """The MCRT effects (``specular``, ``hotspot``) from NAME=VALUE strings or a mapping."""
    parsed = parse_effects(effects)
    wrong = [k for k in parsed if CATALOGUE[k].stage != "mcrt"]
    if wrong:
        raise WaveforestError(f"--effect {', '.join(wrong)}: not an MCRT effect (expected specular or hotspot)")
    return parsed


def write_sigma(result: TraceResult, path: str | Path, i: int = 0, metadata: dict | None = None) -> Path:
    """Write sigma(t) of pulse ``i`` (time, range, sigma, sigma per order) as Parquet or CSV.

    The suffix chooses the format; Parquet files carry ``metadata`` (JSON) in the schema.
    """
    import pyarrow as pa

    from ..io.tables import write_table

    path = Path(path)
    if path.suffix.lower() not in TABLE_SUFFIXES:
        raise WaveforestError(f"{path}: expected a .parquet or .csv output file")
    df = result.frame(i)
    if path.suffix.lower() == ".csv":
        with atomic_path(path) as tmp:
            df.to_csv(tmp, index=False, float_format="%.10g")
        return path
    table = pa.Table.from_pandas(df, preserve_index=False)
    meta = {"waveforest.trace": json.dumps(metadata or {}, default=float)}
    return write_table(table.replace_schema_metadata(meta), path)


def plot_sigma(result: TraceResult, path: str | Path, i: int = 0, title: str = "") -> Path:
    """PNG of sigma(t) of pulse ``i``, total and per scattering order, against range."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
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
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    plt.close(fig)
    return path


def run(scene_path: str | Path | None, out: str | Path, *, species: str | None = None,
        height: float | None = None, range_m: float = 1200.0, scan_zenith_deg: float = 0.0,
        azimuth_deg: float = 0.0, footprint_m: float | None = None, divergence_mrad: float | None = None,
        target=(0.0, 0.0, 0.0), n_rays: int = 30000, max_order: int = 10, bin_ns: float = 0.05,
        viewed_diameter_m: float = 5.0, window_ns: float = DEFAULT_WINDOW_NS, seed: int = 0,
        effects=None, plot: str | Path | None = None, vegetation_options: dict | None = None) -> TraceResult:
    """Trace one pulse through one scene and write its sigma(t) (and a plot).

    Parameters
    ----------
    scene_path : path or None
        PLY scene (faces with rho, tau, kind); None with ``species`` and ``height``.
    out : path
        ``.parquet`` or ``.csv`` output.
    range_m, scan_zenith_deg, azimuth_deg : float
        Sensor distance from ``target`` (m), beam zenith and compass azimuth (degrees).
    footprint_m, divergence_mrad : float, optional
        Collimated 1/e footprint, or divergence of a diverging beam (default 0.15 mrad).
    target : (3,) float
        Point on the beam axis at ``range_m`` (scene coordinates, m).
    n_rays, max_order, bin_ns, viewed_diameter_m, window_ns, seed
        As :func:`waveforest.mcrt.trace`.
    effects : list of "NAME=VALUE" or mapping, optional
        ``specular`` and/or ``hotspot``.
    plot : path, optional
        PNG of sigma(t) by order.

    Returns
    -------
    TraceResult
    """
    out = Path(out)
    if out.suffix.lower() not in TABLE_SUFFIXES:
        raise WaveforestError(f"{out}: expected a .parquet or .csv output file")
    if footprint_m is not None and divergence_mrad is not None:
        raise WaveforestError("trace: give --footprint or --divergence, not both")
    if footprint_m is None and divergence_mrad is None:
        divergence_mrad = DEFAULT_DIVERGENCE_MRAD
    fx = mcrt_effects(effects)
    scene = load_scene(scene_path, species, height, seed, vegetation_options)
    try:
        beams = Beams.toward(np.asarray(target, float), float(range_m), float(scan_zenith_deg),
                             float(azimuth_deg), footprint_m=footprint_m, divergence_mrad=divergence_mrad)
        result = trace(scene, beams, n_rays=n_rays, max_order=max_order, bin_ns=bin_ns,
                       viewed_diameter_m=viewed_diameter_m, seed=seed, window_ns=window_ns,
                       by_order=True, specular=fx.get("specular", CATALOGUE["specular"].off),
                       hotspot=fx.get("hotspot", CATALOGUE["hotspot"].off))
    except ValueError as exc:
        if isinstance(exc, WaveforestError):
            raise
        raise WaveforestError(f"trace: {exc}") from None
    meta = {
        "scene": str(scene_path) if scene_path is not None else f"{species} h={height}",
        "sensor_xyz": beams.origin[0].tolist(), "dir_xyz": beams.direction[0].tolist(),
        "footprint_m": float(beams.footprint_m[0]), "range_m": float(range_m),
        "t0_ns": float(result.t0_ns[0]), "bin_ns": result.bin_ns, "n_rays": n_rays,
        "max_order": max_order, "seed": seed, "effects": fx,
        "order_totals": result.order_totals[0].tolist(), "sigma_dropped": float(result.sigma_dropped[0]),
        "first_hit_counts": result.first_hit_counts[0].tolist(),
    }
    write_sigma(result, out, 0, meta)
    if plot is not None:
        plot_sigma(result, plot)
    return result
