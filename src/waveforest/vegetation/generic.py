"""Generic models of the other low vegetation and of surfaces (Table 1 groups without a
model in Hovi & Korpela 2014); every number in ``structure.csv`` with its source.

- **tufts** (grasses: reedgrass, wavy hairgrass, fresh grass, ripening grass): tufts at random
  positions, ``blades_per_tuft`` blades each from a disc of ``tuft_radius_m``. A blade is a
  flat strip (outline ``blade``) of width ``blade_width_m``; its normal comes from the LAD
  (erectophile: near-vertical blades) and its midrib is the steepest direction of its
  plane, so a blade rises at the plane's inclination. Blade lengths uniform in
  [``blade_length_min_frac`` h, ``blade_length_max_frac`` h], shortened where the tip would
  rise above h or reach further than ``blade_reach_max_m`` sideways; the most upright blade
  of the first tuft reaches h exactly. Tufts are added
  until the target LAI, then every blade's width is scaled by target / realised (heights
  stay exact).
- **layer** (dwarf shrubs: heather, whortleberry, lingonberry, crowberry, Labrador tea):
  ``stems_per_m2`` upright woody stems (heights uniform in [``stem_height_min_frac`` h, h],
  one at h) in ramet clusters (Thomas process of SD ``clump_radius_m`` with
  ``stems_per_clump``), each carrying foliage elements at heights from ``leafy_from`` of the
  stem height to its top within ``crown_radius_m`` of it; element area ``leaf_area_cm2``,
  all equal, their number set by the LAI (exact). Over the ground plane.
- **surface** (mosses, lichens, stone, mineral soil, sand road): a height field with
  micro-relief of RMS ``relief_rms_m`` and correlation length ``relief_corr_m`` on a
  ``grid_m`` grid. Bare surfaces (``carpet_min_m`` = 0) have zero mean height and ignore h;
  moss and lichen carpets are optically thick layers whose mean surface is at
  max(h, ``carpet_min_m``) over the ground plane (the carpet is opaque at 1064 nm within a
  few cm, so its top is the scattering surface).
- **residue** (logging residue): soil micro-relief as for surfaces, branch pieces (lengths
  and diameters uniform in their ranges, random azimuth, tilt within
  +-``piece_tilt_max_deg``, heights up to the pile height h, the highest piece touching h),
  their number set by ``wood_area_index`` (lateral wood area per ground area; pieces are not
  wrapped and may reach up to half their length past the plot edge), and drying
  foliage elements (LAI ``lai``) on the pieces.
"""

from __future__ import annotations

import math

import numpy as np

from waveforest.vegetation.ground import heightfield_triangles, relief_field
from waveforest.vegetation.lad import LeafAngleDistribution, sample_normals
from waveforest.vegetation.leaves import load_outline, place_leaves
from waveforest.vegetation.params import PLOT_AREA_M2, PLOT_HALF_M, SpeciesParams
from waveforest.vegetation.placement import positions, thomas_positions, uniform_positions, wrap
from waveforest.vegetation.plant import Plant, horizontal, isotropic
from waveforest.vegetation.wood import prisms

BATCH_MARGIN = 1.25
"""Tufts drawn per batch, relative to the expected number needed for the target area."""

_UP = np.array([0.0, 0.0, 1.0])


def _disc(n: int, radius: float, rng: np.random.Generator) -> np.ndarray:
    """``n`` points uniform in a disc of ``radius`` around the origin, (n, 2)."""
    r = radius * np.sqrt(rng.random(n))
    a = rng.uniform(0.0, 2.0 * math.pi, n)
    return np.stack([r * np.cos(a), r * np.sin(a)], axis=1)


def build_tufts(p: SpeciesParams, height: float, rng: np.random.Generator,
                lad: LeafAngleDistribution, leaf_area: float, leaf_area_scale: float,
                clumping: float, pool_area: float | None = None) -> Plant:
    """A grass plot: tufts of blades reaching the one-sided leaf area ``leaf_area`` (m^2).

    ``pool_area`` (m^2, default ``leaf_area``): the random draws are those of a plot of that
    leaf area, of which the first tufts that reach ``leaf_area`` are kept. Plots of one seed
    and pool are then nested in their leaf area (a larger one holds every tuft of a smaller
    one), so that a search over the leaf area sees the layer grow, not a new one at every
    value (common random numbers; the understory effect).
    """
    h = float(height)
    target = float(leaf_area) if pool_area is None else max(float(pool_area), float(leaf_area))
    outline = load_outline(p.element)
    per = max(1, int(round(p["blades_per_tuft"])))
    width = p["blade_width_m"]
    lo, hi = p["blade_length_min_frac"] * h, p["blade_length_max_frac"] * h
    reach = p["blade_reach_max_m"]
    area_per_length = outline.area * width / outline.width  # blade area = length x this

    normals, lengths = [], []
    cum, first = 0.0, True
    expected = per * area_per_length * 0.5 * (lo + hi)
    while cum < target:
        m = int(np.ceil(BATCH_MARGIN * (target - cum) / expected)) + 1
        nb = sample_normals(lad, m * per, rng)
        # the steepest in-plane line rises by mz and runs sideways by |n_z| per unit length
        mz = np.sqrt(np.clip(1.0 - nb[:, 2] ** 2, 0.0, 1.0))
        sideways = np.abs(nb[:, 2])
        ln = rng.uniform(lo, hi, m * per)
        with np.errstate(divide="ignore"):
            ln = np.minimum(ln, np.where(mz > 0, h / np.where(mz > 0, mz, 1.0), np.inf))
            ln = np.minimum(ln, np.where(sideways > 0, reach / np.where(sideways > 0, sideways, 1.0), np.inf))
        if first:  # the most upright blade of the first tuft reaches h
            k = int(np.argmax(mz[:per]))
            ln[k] = h / mz[k]
            first = False
        normals.append(nb)
        lengths.append(ln)
        cum += ln.sum() * area_per_length
    normals = np.concatenate(normals)
    lengths = np.concatenate(lengths)
    cum_area = np.cumsum(lengths.reshape(-1, per).sum(axis=1) * area_per_length)
    n_pool = int(np.searchsorted(cum_area, target)) + 1
    n = int(np.searchsorted(cum_area, leaf_area)) + 1
    normals, lengths = normals[: n * per], lengths[: n * per]
    factor = leaf_area / cum_area[n - 1]

    centre = positions(n_pool, rng, clumping, p["plants_per_cluster"])[:n]
    base_xy = wrap(np.repeat(centre, per, axis=0) + _disc(n_pool * per, p["tuft_radius_m"], rng)[: n * per])
    base = np.concatenate([base_xy, np.zeros((n * per, 1))], axis=1)
    wf = width * factor * leaf_area_scale / (lengths * outline.width)
    leaves = place_leaves(outline, base, normals, np.broadcast_to(_UP, normals.shape), lengths, wf)
    areas = outline.area * lengths**2 * wf
    return Plant(leaves=leaves, leaf_area_m2=float(areas.sum()), n_plants=n,
                 element_size_m=float(lengths.max()))


def build_layer(p: SpeciesParams, height: float, rng: np.random.Generator,
                lad: LeafAngleDistribution, leaf_area: float, leaf_area_scale: float,
                clumping: float) -> Plant:
    """A dwarf-shrub layer: clustered stems with foliage elements, ``leaf_area`` m^2 in all."""
    h = float(height)
    outline = load_outline(p.element)
    wf = outline.width_factor(p["leaf_length_width"])
    n_st = max(1, int(round(p["stems_per_m2"] * PLOT_AREA_M2)))
    radius = clumping if clumping > 0 else p["clump_radius_m"]
    xy = thomas_positions(n_st, rng, radius, p["stems_per_clump"]) if radius > 0 \
        else uniform_positions(n_st, rng)
    hs = rng.uniform(p["stem_height_min_frac"] * h, h, n_st)
    hs[0] = h
    p0 = np.concatenate([xy, np.zeros((n_st, 1))], axis=1)
    p1 = np.concatenate([xy, hs[:, None]], axis=1)
    wood = prisms(p0, p1, p["stem_diameter_m"], p["stem_diameter_m"])

    n_l = max(1, int(round(leaf_area / (p["leaf_area_cm2"] * 1e-4))))
    area = leaf_area / n_l * leaf_area_scale
    stem = rng.integers(0, n_st, n_l)
    z = hs[stem] * rng.uniform(p["leafy_from"], 1.0, n_l)
    off = _disc(n_l, p["crown_radius_m"], rng)
    base = np.concatenate([wrap(xy[stem] + off), z[:, None]], axis=1)
    toward = horizontal(np.arctan2(off[:, 1], off[:, 0]))
    normals = sample_normals(lad, n_l, rng)
    ln = outline.length_for_area(np.full(n_l, area), wf)
    leaves = place_leaves(outline, base, normals, toward, ln, wf)
    return Plant(leaves=leaves, leaf_area_m2=area * n_l, wood=wood, n_plants=n_st,
                 element_size_m=float(np.hypot(ln.max(), ln.max() * wf * outline.width)))


def build_surface(p: SpeciesParams, height: float, rng: np.random.Generator) -> Plant:
    """A micro-relief surface: bare (zero mean) or a carpet at max(h, ``carpet_min_m``)."""
    n = max(2, int(round(2.0 * PLOT_HALF_M / p["grid_m"])))
    z = relief_field(rng, p["relief_rms_m"], p["relief_corr_m"], n)
    if p["carpet_min_m"] > 0:
        z = z + max(float(height), p["carpet_min_m"])
    return Plant(surface=heightfield_triangles(z), n_plants=0,
                 element_size_m=float(np.abs(z - z.mean()).max()))


def build_residue(p: SpeciesParams, height: float, rng: np.random.Generator,
                  lad: LeafAngleDistribution, leaf_area: float, leaf_area_scale: float) -> Plant:
    """Logging residue: soil relief, branch pieces up to the pile height, drying foliage."""
    h = float(height)
    soil = build_surface(p, 0.0, rng)
    lmin, lmax = p["piece_length_min_m"], p["piece_length_max_m"]
    dmin, dmax = p["piece_diameter_min_m"], p["piece_diameter_max_m"]
    mean_lateral = math.pi * 0.5 * (dmin + dmax) * 0.5 * (lmin + lmax)
    n = max(1, int(round(p["wood_area_index"] * PLOT_AREA_M2 / mean_lateral)))
    length = rng.uniform(lmin, lmax, n)
    diam = rng.uniform(dmin, dmax, n)
    # tilt within the limit and within what the pile height allows: L |sin t| + d <= h
    fit = np.arcsin(np.clip((h - diam) / length, 0.0, 1.0))
    tmax = np.minimum(math.radians(p["piece_tilt_max_deg"]), fit)
    tilt = rng.uniform(-1.0, 1.0, n) * tmax
    az = rng.uniform(0.0, 2.0 * math.pi, n)
    axis = np.stack([np.cos(tilt) * np.cos(az), np.cos(tilt) * np.sin(az), np.sin(tilt)], axis=1)
    half_z = 0.5 * length * np.abs(np.sin(tilt)) + 0.5 * diam  # vertical half-extent
    zc = rng.uniform(half_z, np.maximum(h - half_z, half_z))
    top = int(np.argmax(zc + half_z))
    zc[top] = max(h - half_z[top], half_z[top])  # the pile reaches h
    centre = np.concatenate([uniform_positions(n, rng), zc[:, None]], axis=1)
    p0 = centre - 0.5 * length[:, None] * axis
    p1 = centre + 0.5 * length[:, None] * axis
    wood = prisms(p0, p1, diam, diam)

    outline = load_outline(p.element)
    wf = outline.width_factor(p["leaf_length_width"])
    n_l = max(1, int(round(leaf_area / (p["leaf_area_cm2"] * 1e-4))))
    area = leaf_area / n_l * leaf_area_scale
    piece = rng.integers(0, n, n_l)
    base = p0[piece] + rng.random(n_l)[:, None] * (p1[piece] - p0[piece])
    base[:, :2] = wrap(base[:, :2])
    normals = sample_normals(lad, n_l, rng)
    ln = outline.length_for_area(np.full(n_l, area), wf)
    leaves = place_leaves(outline, base, normals, isotropic(n_l, rng), ln, wf)
    return Plant(leaves=leaves, leaf_area_m2=area * n_l, wood=wood, surface=soil.surface,
                 n_plants=n, element_size_m=max(float(ln.max()), soil.element_size_m))
