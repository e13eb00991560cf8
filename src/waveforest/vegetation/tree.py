"""Procedural trees: birch (Hovi & Korpela 2014) and the generic broadleaf and conifer trees.

One tree stands at the origin of the 6 x 6 m plot (docs/method.md §(g)). From the height h:

1. **Stem** from (0, 0, 0) to (0, 0, h), diameter ``stem_base_diameter_per_h`` h at the base
   tapering to ``stem_top_diameter_m``.
2. **Crown base** at ``crown_base_frac`` h (birch: 0.2 h, the paper's empty gap below).
3. **Branch whorls** every ``whorl_spacing_m`` from the top down to the crown base (random
   phase), ``branches_per_whorl`` branches each, successive whorls turned by
   ``whorl_divergence_deg``, plus ``branch_azimuth_jitter_deg`` of noise.
4. **Branch length** from the relative depth x in the crown (0 top, 1 crown base): rising as
   (x / x_p)^a to the longest branches ``branch_length_frac`` h at x_p =
   ``crown_widest_depth``, then falling linearly to ``crown_base_length_rel`` of it at the
   crown base; relative SD ``branch_length_cv``. Branches never rise above the top, and
   their reach stays inside the plot.
5. **Branch shape**: zenith angle from ``branch_zenith_top_deg`` (top) to
   ``branch_zenith_base_deg`` (crown base); the outer half bends down by ``branch_bend_deg``;
   diameter ``branch_diameter_base_m`` + ``branch_diameter_per_length`` L at the base.
6. **Sub-branches** every ``sub_spacing_m`` along the outer part of each branch
   (from ``shoot_start_frac`` of its length), ``sub_length_rel`` of the remaining length,
   at ``sub_angle_deg`` from the parent with a random roll.
7. **Shoots** on the foliage axes (upper stem in the crown, the outer part of the branches,
   sub-branches), uniformly by length; ``leaves_per_shoot`` leaves per shoot on average.
8. **Leaves**: total one-sided area from the allometry (:func:`allometric_leaf_area`: for
   birch a published young-birch chain, h -> diameter -> leaf mass -> area; times the
   per-instance jitter), individual areas lognormal around
   ``leaf_area_cm2`` (CV ``leaf_area_cv``) rescaled to sum exactly to A; each leaf on a
   petiole of ``petiole_m`` in an isotropic random direction, pointing away from it; normal
   from the species' LAD with uniform azimuth.

Needle-shoot species (element ``rectangle``: pine, spruce, juniper) carry one shoot per
foliage element: two crossed planes along the shoot axis (the branch direction plus an
isotropic random direction), the first plane's normal from the LAD (Smolander & Stenberg
2003 use the shoot as the basic element; its needle area is half the total needle surface,
Chen & Black 1992).

The paper used the Lintunen et al. (2011) structural model, whose coefficients are not
reproduced here: every number above is in ``resources/vegetation/structure.csv`` with its
source, most of them marked ASSUMPTION (in particular the leaf-area allometry).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from waveforest.vegetation.lad import LeafAngleDistribution, sample_normals
from waveforest.vegetation.leaves import crossed_planes, load_outline, place_leaves
from waveforest.vegetation.params import PLOT_HALF_M, SpeciesParams
from waveforest.vegetation.plant import Plant, isotropic, lognormal_areas, unit_dirs
from waveforest.vegetation.wood import prisms

NEEDLE_SHOOT_ELEMENT = "rectangle"
"""Foliage element name that makes a tree a needle-shoot (conifer) tree."""

STEM_SEGMENTS = 4
"""Prism segments of the stem (discretisation of the taper)."""

MIN_BRANCH_M = 0.02
"""Branches shorter than this are dropped, m."""

REACH_MARGIN_M = 0.3
"""Branches reach at most the plot half-width minus this, m (leaves stay inside)."""

TOP_CLEARANCE = 0.9
"""A branch rises at most this fraction of its distance to the tree top."""


BREAST_HEIGHT_M = 1.3
"""Height of the breast-height diameter, m."""


def allometric_leaf_area(p: SpeciesParams, height: float) -> float:
    """Total one-sided leaf (needle-shoot) area of a tree of height ``height``, m^2.

    Trees whose parameters give the published young-tree chain (birch, and as in Majasalmi
    et al. 2013 the other broadleaves; ``structure.csv`` cites each number):

    1. breast-height diameter from the Naslund (1936) height curve of the Finnish NFI,
       h = 1.3 + (d / (a + b d))^2, inverted: d = a s / (1 - b s), s = sqrt(h - 1.3), cm
       (0 below breast height);
    2. stump diameter d_s = d0 + d1 d, cm (Laasasenaho 1975);
    3. dry leaf mass W = c (10 d_s)^e, kg, d_s in mm (Johansson 1999, as given by
       Majasalmi et al. 2013, Eq. 8; young birches on abandoned farmland);
    4. A = SLA W, SLA in m^2 kg^-1 (Lintunen et al. 2011).

    Other trees: an assumed power law A = a h^b (``foliage_area_a``, ``foliage_area_b``).
    """
    if "leaf_mass_a" not in p.structure:
        return p["foliage_area_a"] * height ** p["foliage_area_b"]
    s = math.sqrt(max(height - BREAST_HEIGHT_M, 0.0))
    d_cm = p["naslund_a"] * s / (1.0 - p["naslund_b"] * s)
    stump_mm = 10.0 * (p["stump_d0_cm"] + p["stump_d1"] * d_cm)
    return p["sla_m2_per_kg"] * p["leaf_mass_a"] * stump_mm ** p["leaf_mass_b"]


def _along(p0, d1, d2, length, s):
    """Point at arc length s of the bent branch (two halves with directions d1, d2)."""
    half = (0.5 * length)[:, None]
    s = s[:, None]
    return np.where(s <= half, p0 + s * d1, p0 + half * d1 + (s - half) * d2)


class _Branches(NamedTuple):
    """Bent first-order branches, k of them: base ``b0``, bend ``b1``, tip ``b2`` (k, 3) m,
    directions ``d1``, ``d2`` of the two halves (k, 3) and ``length`` (k,) m."""

    b0: np.ndarray
    b1: np.ndarray
    b2: np.ndarray
    d1: np.ndarray
    d2: np.ndarray
    length: np.ndarray


def _stem(p: SpeciesParams, h: float) -> np.ndarray:
    """Steps 1-2: the stem from 0 to ``h`` as ``STEM_SEGMENTS`` tapered prisms (triangles)."""
    zs = np.linspace(0.0, h, STEM_SEGMENTS + 1)
    d_stem = np.linspace(max(p["stem_base_diameter_per_h"] * h, p["stem_top_diameter_m"]),
                         p["stem_top_diameter_m"], STEM_SEGMENTS + 1)
    stem_pts = np.stack([np.zeros_like(zs), np.zeros_like(zs), zs], axis=1)
    return prisms(stem_pts[:-1], stem_pts[1:], d_stem[:-1], d_stem[1:])


def _branches(p: SpeciesParams, h: float, crown: float, rng: np.random.Generator) -> _Branches:
    """Steps 3-5: whorls, branch lengths from the crown profile, bent branches.

    Branches are capped so that they stay below ``TOP_CLEARANCE`` of the height above them
    and within the plot (``PLOT_HALF_M - REACH_MARGIN_M``); those shorter than
    ``MIN_BRANCH_M`` are dropped. Draws from ``rng``: whorl phase, first azimuth, azimuth
    jitter, length noise (in this order).
    """
    # 3. whorls
    spacing = p["whorl_spacing_m"]
    phase = rng.random()  # the top whorl lies phase * spacing below the top
    n_wh = max(0, int(np.floor(crown / spacing - phase)) + 1)
    z_wh = h - (np.arange(n_wh) + phase) * spacing  # all >= the crown base
    n_per = max(1, int(round(p["branches_per_whorl"])))
    az0 = rng.uniform(0.0, 2.0 * math.pi)
    kk = np.arange(z_wh.size)
    az = (az0 + kk[:, None] * math.radians(p["whorl_divergence_deg"])
          + np.arange(n_per)[None, :] * (2.0 * math.pi / n_per)).ravel()
    az = az + rng.normal(0.0, math.radians(p["branch_azimuth_jitter_deg"]), az.size)
    zb = np.repeat(z_wh, n_per)

    # 4. branch lengths from the crown profile
    x = (h - zb) / crown if crown > 0 else np.zeros_like(zb)
    xp, a = p["crown_widest_depth"], p["crown_top_exponent"]
    lmax = p["branch_length_frac"] * h
    rel = np.where(
        x <= xp,
        (np.clip(x, 0, None) / xp) ** a if xp > 0 else 1.0,
        1.0 - (1.0 - p["crown_base_length_rel"]) * (x - xp) / max(1.0 - xp, 1e-12),
    )
    length = lmax * rel * np.exp(rng.normal(0.0, p["branch_length_cv"], zb.size))
    zen = np.radians(p["branch_zenith_top_deg"]
                     + (p["branch_zenith_base_deg"] - p["branch_zenith_top_deg"]) * x)
    cz, sz = np.cos(zen), np.sin(zen)
    with np.errstate(divide="ignore"):
        cap_top = np.where(cz > 0, TOP_CLEARANCE * (h - zb) / np.where(cz > 0, cz, 1.0), np.inf)
        cap_reach = np.where(sz > 0, (PLOT_HALF_M - REACH_MARGIN_M) / np.where(sz > 0, sz, 1.0), np.inf)
    length = np.minimum(length, np.minimum(cap_top, cap_reach))
    keep = length >= MIN_BRANCH_M
    zb, az, zen, length = zb[keep], az[keep], zen[keep], length[keep]

    # 5. bent branches: two halves
    bend = math.radians(p["branch_bend_deg"])
    d1 = unit_dirs(zen, az)
    d2 = unit_dirs(np.minimum(zen + bend, math.pi), az)
    b0 = np.stack([np.zeros_like(zb), np.zeros_like(zb), zb], axis=1)
    b1 = b0 + 0.5 * length[:, None] * d1
    b2 = b1 + 0.5 * length[:, None] * d2
    return _Branches(b0, b1, b2, d1, d2, length)


def _branch_wood(p: SpeciesParams, br: _Branches) -> np.ndarray | None:
    """Step 5: prisms of the two halves of every branch (None without branches).

    Diameter ``dmin + branch_diameter_per_length * l`` at the base (``l``: branch length),
    half of that excess at the bend, ``dmin = branch_diameter_base_m`` at the tip.
    """
    if not br.length.size:
        return None
    dmin = p["branch_diameter_base_m"]
    dbase = dmin + p["branch_diameter_per_length"] * br.length
    dmid = dmin + p["branch_diameter_per_length"] * 0.5 * br.length
    return prisms(np.concatenate([br.b0, br.b1]), np.concatenate([br.b1, br.b2]),
                  np.concatenate([dbase, dmid]), np.concatenate([dmid, np.full_like(dmid, dmin)]))


def _sub_branches(p: SpeciesParams, h: float, br: _Branches,
                  rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step 6: sub-branches on the outer part of each branch.

    Returns start points ``sp0``, end points ``sp1`` (k, 3) m and lengths ``sl`` (k,) m.
    Sub-branches are shortened to stay within ``TOP_CLEARANCE`` of the top and above the
    ground; shorter than ``MIN_BRANCH_M`` are dropped. Draws from ``rng``: positions along
    the branch, then roll directions.
    """
    length = br.length
    start = p["shoot_start_frac"]
    sub_sp = p["sub_spacing_m"]
    n_sub = np.floor((1.0 - start) * length / sub_sp).astype(np.int64)
    owner = np.repeat(np.arange(length.size), n_sub)
    idx = np.arange(owner.size) - np.repeat(np.cumsum(n_sub) - n_sub, n_sub)
    s = start * length[owner] + (idx + rng.random(owner.size)) * sub_sp
    s = np.minimum(s, length[owner])
    sp0 = _along(br.b0[owner], br.d1[owner], br.d2[owner], length[owner], s)
    par = np.where((s <= 0.5 * length[owner])[:, None], br.d1[owner], br.d2[owner])
    roll = isotropic(owner.size, rng)
    perp = roll - np.sum(roll * par, axis=1, keepdims=True) * par
    perp /= np.maximum(np.linalg.norm(perp, axis=1, keepdims=True), 1e-12)
    ang = math.radians(p["sub_angle_deg"])
    sd = math.cos(ang) * par + math.sin(ang) * perp
    sl = p["sub_length_rel"] * (length[owner] - s)
    dz = sl * sd[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        up = np.where(dz > 0, (TOP_CLEARANCE * (h - sp0[:, 2])) / dz, 1.0)
        down = np.where(dz < 0, sp0[:, 2] / -dz, 1.0)
    sl = sl * np.clip(np.minimum(up, down), 0.0, 1.0)
    ok = sl >= MIN_BRANCH_M
    sp0, sd, sl = sp0[ok], sd[ok], sl[ok]
    return sp0, sp0 + sl[:, None] * sd, sl


def _foliage_axes(p: SpeciesParams, h: float, z_cb: float, br: _Branches, sp0: np.ndarray,
                  sp1: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Step 7: segments that carry shoots: the crown part of the stem, the outer branch
    parts and the sub-branches.

    Returns start points ``a0`` (k, 3), vectors ``seg`` (k, 3), lengths ``seg_len`` (k,) and
    unit directions ``seg_dir`` (k, 3) of the non-degenerate segments, m.
    """
    start = p["shoot_start_frac"]
    inner = _along(br.b0, br.d1, br.d2, br.length, start * br.length)
    ax0 = [np.array([[0.0, 0.0, z_cb]]), br.b1]
    ax1 = [np.array([[0.0, 0.0, h]]), br.b2]
    if start < 0.5:  # the shoots start on the first half
        ax0.append(inner)
        ax1.append(br.b1)
    ax0.append(sp0)
    ax1.append(sp1)
    a0, a1 = np.concatenate(ax0), np.concatenate(ax1)
    seg = a1 - a0
    seg_len = np.linalg.norm(seg, axis=1)
    valid = seg_len > 0
    a0, seg, seg_len = a0[valid], seg[valid], seg_len[valid]
    return a0, seg, seg_len, seg / seg_len[:, None]


def _tree_leaves(p: SpeciesParams, axes: tuple, lad: LeafAngleDistribution, leaf_area: float,
                 leaf_area_scale: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step 8: shoots placed along the foliage axes (by length), leaves on the shoots.

    ``round(leaf_area / leaf_area_cm2)`` leaves with lognormal areas summing to
    ``leaf_area`` (times ``leaf_area_scale``); needle shoots are two crossed planes per
    shoot along its axis, broadleaves one per shoot and the rest at random on a petiole.
    Returns the leaf triangles, the (n,) leaf areas, m^2, and the (n,) leaf lengths, m.
    """
    a0, seg, seg_len, seg_dir = axes
    outline = load_outline(p.element)
    needles = p.element == NEEDLE_SHOOT_ELEMENT
    wf = outline.width_factor(p["leaf_length_width"])
    mean_area = p["leaf_area_cm2"] * 1e-4
    n_leaves = max(1, int(round(leaf_area / mean_area)))
    areas = lognormal_areas(n_leaves, leaf_area, p["leaf_area_cv"], rng) * leaf_area_scale
    n_shoots = n_leaves if needles else max(1, int(round(n_leaves / p["leaves_per_shoot"])))
    which = rng.choice(seg_len.size, size=n_shoots, p=seg_len / seg_len.sum())
    shoot_pos = a0[which] + rng.random(n_shoots)[:, None] * seg[which]
    if needles:
        leaf_shoot = np.arange(n_leaves)
    else:  # every shoot gets one leaf, the rest at random
        leaf_shoot = np.concatenate([np.arange(min(n_shoots, n_leaves)),
                                     rng.integers(0, n_shoots, max(0, n_leaves - n_shoots))])
    iso = isotropic(n_leaves, rng)
    normals = sample_normals(lad, n_leaves, rng)
    if needles:
        toward = seg_dir[which][leaf_shoot] + iso
        ln = outline.length_for_area(0.5 * areas, wf)
        leaves = crossed_planes(outline, shoot_pos[leaf_shoot], normals, toward, ln, wf)
    else:
        base = shoot_pos[leaf_shoot] + p["petiole_m"] * iso
        ln = outline.length_for_area(areas, wf)
        leaves = place_leaves(outline, base, normals, iso, ln, wf)
    return leaves, areas, ln


def build_tree(p: SpeciesParams, height: float, rng: np.random.Generator,
               lad: LeafAngleDistribution, leaf_area: float, leaf_area_scale: float) -> Plant:
    """One tree of species ``p`` at the origin (steps 1-8 of the module docstring).

    Parameters
    ----------
    p : SpeciesParams
        A ``tree`` species.
    height : float, m
    rng : numpy.random.Generator
    lad : LeafAngleDistribution
        Leaf (first shoot plane) inclinations.
    leaf_area : float, m^2
        Total one-sided leaf area to realise (the allometry times any jitter).
    leaf_area_scale : float
        Factor on every leaf's area after the structure is fixed (sensitivity sweeps).

    Returns
    -------
    Plant
    """
    h = float(height)
    z_cb = p["crown_base_frac"] * h
    wood = [_stem(p, h)]
    br = _branches(p, h, h - z_cb, rng)
    branch_wood = _branch_wood(p, br)
    if branch_wood is not None:
        wood.append(branch_wood)
    sp0, sp1, sl = _sub_branches(p, h, br, rng)
    if sl.size:
        dmin = p["branch_diameter_base_m"]
        wood.append(prisms(sp0, sp1, dmin + p["branch_diameter_per_length"] * sl, dmin))
    axes = _foliage_axes(p, h, z_cb, br, sp0, sp1)
    leaves, areas, ln = _tree_leaves(p, axes, lad, leaf_area, leaf_area_scale, rng)

    outline = load_outline(p.element)
    width = float(ln.max()) * outline.width_factor(p["leaf_length_width"]) * outline.width
    return Plant(
        leaves=leaves,
        leaf_area_m2=float(areas.sum()),
        wood=np.concatenate(wood),
        n_plants=1,
        element_size_m=float(np.hypot(ln.max(), width) + p["petiole_m"]),
    )
