"""``waveforest trace``: sigma(t) of one pulse through one scene (METHOD.md d)."""

from __future__ import annotations

import time

import click

from ..cliutil import stage_options


@click.command("trace")
@click.argument("scene", required=False, type=click.Path(dir_okay=False))
@click.option("--out", "out", required=True, type=click.Path(dir_okay=False),
              help="Output sigma(t) table, .parquet or .csv (time_ns, range_m, sigma, sigma per order).")
@click.option("--species", default=None, help="Trace a vegetation instance of this species slug instead of SCENE.")
@click.option("--height", type=float, default=None, help="Height of the vegetation instance, m (with --species).")
@click.option("--range", "range_m", type=float, default=1200.0, show_default=True,
              help="Sensor distance from the target point, m.")
@click.option("--scan-zenith", type=float, default=0.0, show_default=True, help="Beam zenith angle, degrees.")
@click.option("--azimuth", type=float, default=0.0, show_default=True,
              help="Compass azimuth of the beam's travel, degrees clockwise from north (+y).")
@click.option("--footprint", type=float, default=None,
              help="1/e footprint diameter of a collimated beam, m (default: --divergence 0.15).")
@click.option("--divergence", type=float, default=None, help="1/e beam divergence, mrad (diverging beam).")
@click.option("--target-x", type=float, default=0.0, show_default=True, help="Target point x, m (scene coordinates).")
@click.option("--target-y", type=float, default=0.0, show_default=True, help="Target point y, m.")
@click.option("--target-z", type=float, default=0.0, show_default=True, help="Target point z, m.")
@click.option("--rays", type=int, default=None, help="Rays per pulse (default: config mcrt.n_rays).")
@click.option("--orders", type=int, default=None, help="Highest scattering order (default: config mcrt.max_order).")
@click.option("--effect", "effects", multiple=True, metavar="NAME=VALUE",
              help="MCRT effect: specular=FRACTION or hotspot=FACTOR (repeatable).")
@click.option("--plot", type=click.Path(dir_okay=False), default=None, help="PNG of sigma(t) by scattering order.")
@stage_options
def trace(scene, out, species, height, range_m, scan_zenith, azimuth, footprint, divergence,
          target_x, target_y, target_z, rays, orders, effects, plot, cfg):
    """Trace one LiDAR pulse through SCENE (a PLY whose faces carry rho, tau, kind) -> sigma(t).

    Writes sigma(t) on the fine time grid (config mcrt.bin_ns) with its per-order split,
    and optionally a plot. Example:

      waveforest trace canopy.ply --out sigma.parquet --range 1200 --scan-zenith 10 --plot sigma.png
    """
    from .runner import run

    m = cfg["mcrt"]
    veg = cfg["vegetation"]
    t = time.perf_counter()
    res = run(
        scene, out, species=species, height=height, range_m=range_m, scan_zenith_deg=scan_zenith,
        azimuth_deg=azimuth, footprint_m=footprint, divergence_mrad=divergence,
        target=(target_x, target_y, target_z),
        n_rays=rays if rays is not None else m["n_rays"],
        max_order=orders if orders is not None else m["max_order"],
        bin_ns=m["bin_ns"], viewed_diameter_m=m["viewed_diameter_m"], window_ns=m["window_ns"],
        seed=cfg["seed"], effects=list(effects), plot=plot,
        vegetation_options={k: veg[k] for k in ("ground_rho", "lai_jitter")},
    )
    dt = time.perf_counter() - t
    o = res.order_totals[0]
    click.echo(
        f"wrote {out}: 1 pulse, {res.n_bins} bins of {res.bin_ns:g} ns, sigma {res.total[0]:.5g} "
        f"(order 1 {o[0]:.5g}, dropped {res.sigma_dropped[0]:.3g}), {res.n_rays} rays, {dt:.2f} s"
        + (f"; plot {plot}" if plot else "")
    )
