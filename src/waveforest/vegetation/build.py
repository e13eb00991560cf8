"""A vegetation scene from a spec: species, height, seed and the optional effects.

``build_scene(species, height, seed, ...)`` returns a :class:`~waveforest.scene.Scene` in local
coordinates: a 6 x 6 m plot (x, y in [-3, 3]), ground plane at z = 0 (two triangles, kind 0,
rho ``ground_rho``, tau 0), the plant or the sample centred at the origin; leaves kind 1,
woody parts kind 2, moss/lichen carpets kind 3, bare surfaces kind 0.

Random streams: the seed's named stream ``scene_build`` (:func:`waveforest.rng.named_generators`)
gives independent streams for the plant, the understory and the instance's LAI jitter, so
switching the understory on does not change the plant, and the same arguments give an
identical scene.

Effects (``waveforest.effects``, each off by default):

- ``understory``: LAI of a grass layer ``effects.UNDERSTORY_HEIGHT_M`` tall under *trees*,
  built with the ``fresh_grass_low`` model and optics (no-op for low vegetation and
  surfaces, which already fill the space near the ground); the layers of one seed are nested
  in their LAI up to :data:`UNDERSTORY_POOL_LAI` (a higher LAI adds tufts to the same ones).
- ``clumping``: Thomas-process cluster radius, m, for shoot-based plots (shoots, tufts,
  dwarf-shrub stems; for dwarf shrubs it replaces their own ramet-cluster radius); no-op
  for trees (one plant) and surfaces.
- ``lad_shift``: shift of the mean leaf inclination, degrees: the species LAD replaced by the
  beta form with the same concentration and the shifted mean, clipped to [0, 90]
  (:meth:`LeafAngleDistribution.shifted`).
- ``leaf_albedo``: factor on leaf rho and tau. If rho + tau would exceed 1, tau is lowered to
  1 - rho (energy conservation; rho, which sets the first order, keeps its scaled value).

Other parameters: ``mean_leaf_angle`` (degrees) replaces the species LAD by the beta form
with that mean (the species' concentration; at 0 or 90 all leaves lie at that angle), applied
before ``lad_shift``. This is the choice made for the sensitivity sweep (docs/method.md §(i2)): the
paper's alternative "all leaves at the angle" is the limit of a concentration -> infinity
and is not used because it makes leaves of a planar canopy exactly parallel.
``leaf_area_scale`` multiplies every leaf's area after the structure (leaf count, shoot count)
is fixed, so the total leaf area and LAI scale with it. ``leaf_rho``/``leaf_tau`` replace the
species' leaf optics (before ``leaf_albedo``). ``lai_jitter`` is the relative uniform variation
(+-) of the instance's LAI (plots) or total leaf area (trees) (docs/method.md §(g): "small random LAI
variation", amount UNSPECIFIED; 10 % by default).
"""

from __future__ import annotations

import inspect
import math
from dataclasses import dataclass

import numpy as np

from waveforest.constants import KIND_GROUND, KIND_LEAF, KIND_WOOD
from waveforest.effects import CATALOGUE, UNDERSTORY_HEIGHT_M
from waveforest.errors import WaveforestError
from waveforest.rng import named_generators
from waveforest.scene import Scene
from waveforest.vegetation.generic import build_layer, build_residue, build_surface, build_tufts
from waveforest.vegetation.ground import ground_plane
from waveforest.vegetation.herbs import build_shoots
from waveforest.vegetation.lad import LeafAngleDistribution, lad_by_name
from waveforest.vegetation.params import PLOT_AREA_M2, SpeciesParams, species_params
from waveforest.vegetation.plant import Plant
from waveforest.vegetation.tree import allometric_leaf_area, build_tree


class VegetationError(WaveforestError):
    """An invalid vegetation spec (species, height or parameter)."""


UNDERSTORY_SPECIES = "fresh_grass_low"
"""Model and optics of the understory layer (effect ``understory``)."""

UNDERSTORY_POOL_LAI = CATALOGUE["understory"].bounds[1]
"""The understory layers of one seed are nested up to this LAI (``build_tufts``'s pool: one
layer that grows with the effect's value, over its whole search range)."""

_RHO_TAU_SLACK = 1e-9


@dataclass(frozen=True)
class Built:
    """A built vegetation instance and what it was built to.

    Attributes
    ----------
    scene : Scene
    species : str
    height : float, m
    seed : int
    target_leaf_area_m2 : float
        One-sided leaf area the species model was asked for: allometry (trees) or LAI x
        36 m^2 (plots), times the instance's jitter factor and ``leaf_area_scale``; 0 for
        surfaces.
    leaf_area_m2 : float
        Realised one-sided leaf area of the species model (without the understory).
    jitter_factor : float
        The instance's relative LAI / leaf-area factor, in [1 - lai_jitter, 1 + lai_jitter].
    lad : LeafAngleDistribution or None
        Leaf inclination distribution used (None for surfaces).
    leaf_rho, leaf_tau : float
        Leaf optics used (NaN for surfaces).
    n_plants : int
        Trees, shoots, tufts, stems or residue pieces.
    element_size_m : float
        Size of the largest foliage element or of the surface relief: the scene top equals
        the requested height within this.
    understory_leaf_area_m2 : float
        One-sided leaf area of the understory layer.
    """

    scene: Scene
    species: str
    height: float
    seed: int
    target_leaf_area_m2: float
    leaf_area_m2: float
    jitter_factor: float
    lad: LeafAngleDistribution | None
    leaf_rho: float
    leaf_tau: float
    n_plants: int
    element_size_m: float
    understory_leaf_area_m2: float

    @property
    def target_lai(self) -> float:
        """Target LAI of the species model over the 6 x 6 m plot."""
        return self.target_leaf_area_m2 / PLOT_AREA_M2


def _check(name: str, value, lo=-math.inf, hi=math.inf, lo_open=False) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise VegetationError(f"{name}: expected a number, got {value!r}") from None
    bad = not math.isfinite(v) or v > hi or (v <= lo if lo_open else v < lo)
    if bad:
        left = "(" if lo_open else "["
        raise VegetationError(f"{name}: expected a value in {left}{lo}, {hi}], got {value!r}")
    return v


def _leaf_optics(p, leaf_rho, leaf_tau, leaf_albedo) -> tuple[float, float]:
    rho = p.leaf_rho if leaf_rho is None else _check("leaf_rho", leaf_rho, 0.0, 1.0)
    tau = p.leaf_tau if leaf_tau is None else _check("leaf_tau", leaf_tau, 0.0, 1.0)
    if rho + tau > 1.0 + _RHO_TAU_SLACK:
        raise VegetationError(f"leaf_rho + leaf_tau = {rho + tau:.3f} for {p.slug}: expected <= 1")
    rho, tau = rho * leaf_albedo, tau * leaf_albedo
    if rho > 1.0:
        raise VegetationError(f"leaf_albedo {leaf_albedo}: leaf rho would be {rho:.3f} > 1")
    return rho, min(tau, 1.0 - rho)


def _species_plant(p: SpeciesParams, h: float, rng: np.random.Generator, lad: LeafAngleDistribution | None,
                   jitter: float, leaf_area_scale: float, clumping: float) -> tuple[Plant, float]:
    """The plant(s) of the species' model family and the one-sided leaf area asked of it, m^2.

    The target is the allometry (trees, :func:`allometric_leaf_area`) or LAI x
    :data:`PLOT_AREA_M2` (plot models), times ``jitter`` and ``leaf_area_scale``; 0 for
    surfaces.
    """
    target = 0.0
    if p.model == "tree":
        target = allometric_leaf_area(p, h) * jitter
        plant = build_tree(p, h, rng, lad, target, leaf_area_scale)
    elif p.model == "shoots":
        target = p["lai"] * PLOT_AREA_M2 * jitter
        plant = build_shoots(p, h, rng, lad, target, leaf_area_scale, clumping)
    elif p.model == "tufts":
        target = p["lai"] * PLOT_AREA_M2 * jitter
        plant = build_tufts(p, h, rng, lad, target, leaf_area_scale, clumping)
    elif p.model == "layer":
        target = p["lai"] * PLOT_AREA_M2 * jitter
        plant = build_layer(p, h, rng, lad, target, leaf_area_scale, clumping)
    elif p.model == "residue":
        target = p["lai"] * PLOT_AREA_M2 * jitter
        plant = build_residue(p, h, rng, lad, target, leaf_area_scale)
    else:
        plant = build_surface(p, h, rng)
    return plant, target * leaf_area_scale


def _understory(lai: float, rng: np.random.Generator) -> tuple[tuple, float]:
    """The understory layer of LAI ``lai`` under a tree: the scene part ``(triangles, rho,
    tau, KIND_LEAF)`` and its one-sided leaf area, m^2, of :data:`UNDERSTORY_SPECIES` tufts, :data:`UNDERSTORY_HEIGHT_M` tall,
    drawn from a pool of :data:`UNDERSTORY_POOL_LAI` (nested layers for one seed)."""
    up = species_params(UNDERSTORY_SPECIES)
    under = build_tufts(up, UNDERSTORY_HEIGHT_M, rng, lad_by_name(up.lad), lai * PLOT_AREA_M2, 1.0, 0.0,
                        pool_area=UNDERSTORY_POOL_LAI * PLOT_AREA_M2)
    return (under.leaves, up.leaf_rho, up.leaf_tau, KIND_LEAF), under.leaf_area_m2


def _scene_of(parts: list[tuple]) -> Scene:
    """One :class:`Scene` of ``(triangles, rho, tau, kind)`` parts, in their order."""
    counts = [len(t) for t, *_ in parts]
    return Scene(
        np.concatenate([t for t, *_ in parts]),
        np.repeat(np.array([r for _, r, _, _ in parts], dtype=np.float32), counts),
        np.repeat(np.array([t for _, _, t, _ in parts], dtype=np.float32), counts),
        np.repeat(np.array([k for *_, k in parts], dtype=np.uint8), counts),
    )


def build(species: str, height: float, seed: int, *, ground_rho: float = 0.30,
          lai_jitter: float = 0.10, understory: float = 0.0, clumping: float = 0.0,
          lad_shift: float = 0.0, leaf_albedo: float = 1.0, leaf_area_scale: float = 1.0,
          mean_leaf_angle: float | None = None, leaf_rho: float | None = None,
          leaf_tau: float | None = None, ground: bool = True) -> Built:
    """Build one vegetation instance of ``species`` with field height ``height``.

    Parameters
    ----------
    species : str
        Species slug (:func:`species_table`); unknown slugs are an error listing the valid ones.
    height : float, m
        Field (maximum) height of the sample; the scene top equals it within one foliage
        element. Accepted range per species in ``species.csv`` (0 for bare surfaces).
    seed : int
        Seed of every random draw (same arguments -> identical scene).
    ground_rho : float
        Reflectance of the Lambertian ground plane (docs/method.md §(g): 0.30).
    lai_jitter : float
        Relative uniform (+-) variation of the instance's LAI / total leaf area.
    understory, clumping, lad_shift, leaf_albedo : float
        Effects of :mod:`waveforest.effects` (see the module docstring); off by default.
    leaf_area_scale : float
        Factor on every leaf's area (sensitivity sweep, 0.5-1.5).
    mean_leaf_angle : float or None, degrees
        Replace the species LAD by the beta form with this mean.
    leaf_rho, leaf_tau : float or None
        Replace the species' leaf reflectance / transmittance at 1064 nm.
    ground : bool
        Include the ground plane (bare surfaces: their surface).

    Returns
    -------
    Built
        The scene and the targets it was built to (for checks and reports).
    """
    if not isinstance(species, str):
        raise VegetationError(f"species: expected a slug string, got {species!r}")
    p = species_params(species)
    h = _check("height", height)
    if not (p.h_min_ok <= h <= p.h_max_ok):
        raise VegetationError(
            f"height {height!r} m for {species}: expected {p.h_min_ok:g} to {p.h_max_ok:g} m"
        )
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise VegetationError(f"seed: expected a non-negative integer, got {seed!r}")
    ground_rho = _check("ground_rho", ground_rho, 0.0, 1.0)
    lai_jitter = _check("lai_jitter", lai_jitter, 0.0, 0.5)
    understory = _check("understory", understory, 0.0)
    clumping = _check("clumping", clumping, 0.0)
    lad_shift = _check("lad_shift", lad_shift, -90.0, 90.0)
    leaf_albedo = _check("leaf_albedo", leaf_albedo, 0.0, lo_open=True)
    leaf_area_scale = _check("leaf_area_scale", leaf_area_scale, 0.0, lo_open=True)
    if mean_leaf_angle is not None:
        mean_leaf_angle = _check("mean_leaf_angle", mean_leaf_angle, 0.0, 90.0)

    rng, under_rng, jitter_rng = named_generators("scene_build", int(seed), 3)
    jitter = 1.0 + lai_jitter * (2.0 * jitter_rng.random() - 1.0)

    lad = lad_by_name(p.lad) if p.lad else None
    if lad is not None:
        if mean_leaf_angle is not None:
            lad = lad.with_mean(mean_leaf_angle)
        lad = lad.shifted(lad_shift)
    if p.model == "surface":
        rho = tau = float("nan")
    else:
        rho, tau = _leaf_optics(p, leaf_rho, leaf_tau, leaf_albedo)

    plant, target = _species_plant(p, h, rng, lad, jitter, leaf_area_scale, clumping)
    parts = []  # (triangles, rho, tau, kind)
    if plant.leaves.size:
        parts.append((plant.leaves, rho, tau, KIND_LEAF))
    if plant.wood.size:
        parts.append((plant.wood, p.wood_rho, p.wood_tau, KIND_WOOD))
    surface_kind = p.surface_kind
    if plant.surface.size and (ground or surface_kind != KIND_GROUND):
        parts.append((plant.surface, p.surface_rho, 0.0, surface_kind))

    under_area = 0.0
    if understory > 0 and p.model == "tree":
        under, under_area = _understory(understory, under_rng)
        parts.append(under)

    if ground and surface_kind != KIND_GROUND:
        g = ground_plane(ground_rho)
        parts.append((g.triangles, ground_rho, 0.0, KIND_GROUND))
    if not parts:
        raise VegetationError(f"{species} is a bare surface: ground=False leaves an empty scene")
    scene = _scene_of(parts)
    return Built(
        scene=scene,
        species=species,
        height=h,
        seed=int(seed),
        target_leaf_area_m2=float(target),
        leaf_area_m2=float(plant.leaf_area_m2),
        jitter_factor=float(jitter),
        lad=lad,
        leaf_rho=rho,
        leaf_tau=tau,
        n_plants=plant.n_plants,
        element_size_m=plant.element_size_m,
        understory_leaf_area_m2=under_area,
    )


def build_scene(species: str, height: float, seed: int, **options) -> Scene:
    """The :class:`Scene` of :func:`build` (the same parameters and defaults): triangles with
    per-triangle rho, tau and kind (0 ground, 1 leaf, 2 wood, 3 other)."""
    return build(species, height, seed, **options).scene


build_scene.__signature__ = inspect.signature(build).replace(return_annotation="Scene")
