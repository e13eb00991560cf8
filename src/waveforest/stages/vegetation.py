"""``waveforest vegetation``: one vegetation instance as a PLY scene and a PNG picture."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import click
import numpy as np

from waveforest.cliutil import stage_options
from waveforest.effects import CATALOGUE, parse_effects
from waveforest.errors import WaveforestError
from waveforest.scene import write_ply
from waveforest.vegetation.build import build
from waveforest.vegetation.gaps import leaf_area_index
from waveforest.vegetation.render import render_png


@dataclass(frozen=True)
class VegetationSummary:
    """What ``run`` wrote."""

    ply: Path
    png: Path | None
    n_triangles: int
    kind_counts: tuple[int, int, int, int]
    lai: float
    top_m: float


def run(species: str, height: float, seed: int, out: str | Path, *, ground_rho: float, lai_jitter: float,
        png: str | Path | None = None, effects: dict | None = None, **params) -> VegetationSummary:
    """Build one instance, write it as PLY (faces carry rho, tau, kind) and optionally a PNG.

    Parameters
    ----------
    species, height, seed
        As for :func:`waveforest.vegetation.build_scene`.
    out : path
        PLY file to write.
    png : path or None
        PNG picture to write (None: none).
    ground_rho, lai_jitter
        Ground reflectance and LAI jitter (config section ``vegetation``).
    effects : dict, optional
        Vegetation effects name -> value (understory, clumping, lad_shift, leaf_albedo).
    **params
        Further keyword arguments of ``build_scene`` (mean_leaf_angle, leaf_area_scale,
        leaf_rho, leaf_tau, ground).

    Returns
    -------
    VegetationSummary
    """
    effects = dict(effects or {})
    wrong = [k for k in effects if CATALOGUE[k].stage != "vegetation"]
    if wrong:
        raise WaveforestError(
            f"effect {', '.join(wrong)}: acts in {CATALOGUE[wrong[0]].stage}, not in the vegetation; "
            f"vegetation effects are {', '.join(k for k, e in CATALOGUE.items() if e.stage == 'vegetation')}"
        )
    built = build(species, height, seed, ground_rho=ground_rho, lai_jitter=lai_jitter,
                  **effects, **params)
    scene = built.scene
    ply = write_ply(scene, out)
    png_path = None
    if png is not None:
        png_path = render_png(scene, png, title=f"{species}, h = {height:g} m, seed {seed}")
    counts = np.bincount(scene.kind, minlength=4)
    return VegetationSummary(ply=Path(ply), png=png_path, n_triangles=len(scene),
                             kind_counts=tuple(int(c) for c in counts[:4]),
                             lai=leaf_area_index(scene), top_m=float(scene.bounds[1, 2]))


@click.command("vegetation")
@click.option("--species", required=True, help="Species slug (e.g. birch, raspberry, fireweed, scots_pine).")
@click.option("--height", type=click.FloatRange(min=0, min_open=True), required=True, help="Field (maximum) height of the sample, m.")
@click.option("--out", "out", type=click.Path(dir_okay=False), required=True, help="PLY scene to write.")
@click.option("--png", type=click.Path(dir_okay=False), default=None,
              help="PNG picture to write (default: beside --out, same stem).")
@click.option("--no-png", is_flag=True, help="Do not write a picture.")
@click.option("--effect", "effect_items", multiple=True, metavar="NAME=VALUE",
              help="Vegetation effect: understory, clumping, lad_shift or leaf_albedo (repeatable).")
@click.option("--mean-leaf-angle", type=float, default=None, help="Replace the LAD by a beta form with this mean, deg.")
@click.option("--leaf-area-scale", type=float, default=1.0, show_default=True, help="Factor on every leaf's area.")
@click.option("--leaf-rho", type=float, default=None, help="Leaf reflectance at 1064 nm (default: species value).")
@click.option("--leaf-tau", type=float, default=None, help="Leaf transmittance at 1064 nm (default: species value).")
@click.option("--no-ground", is_flag=True, help="Leave out the ground plane.")
@stage_options
def vegetation(species, height, out, png, no_png, effect_items, mean_leaf_angle, leaf_area_scale,
               leaf_rho, leaf_tau, no_ground, cfg):
    """Build one vegetation instance (docs/method.md §(g)) and write it as a PLY scene.

    The faces carry rho, tau and kind (0 ground, 1 leaf, 2 wood, 3 other), as
    `waveforest trace` reads them. The seed is the config seed (or --seed).

    Example:

    \b
    waveforest vegetation --species birch --height 3 --out birch.ply
    """
    if Path(out).suffix.lower() != ".ply":
        raise click.BadParameter(f"{out}: expected a .ply file name", param_hint="'--out'")
    png_path = None if no_png else (png or Path(out).with_suffix(".png"))
    veg = cfg["vegetation"]
    summary = run(species, height, cfg["seed"], out, png=png_path, ground_rho=veg["ground_rho"],
                  lai_jitter=veg["lai_jitter"], effects=parse_effects(list(effect_items)),
                  mean_leaf_angle=mean_leaf_angle, leaf_area_scale=leaf_area_scale,
                  leaf_rho=leaf_rho, leaf_tau=leaf_tau, ground=not no_ground)
    g, leaf, wood, other = summary.kind_counts
    extra = f" and {summary.png}" if summary.png else ""
    click.echo(f"wrote {summary.ply}{extra}: {summary.n_triangles} triangles "
               f"(leaf {leaf}, wood {wood}, other {other}, ground {g}), "
               f"LAI {summary.lai:.2f}, top {summary.top_m:.2f} m")
