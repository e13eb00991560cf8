"""Herb plots of shoots: raspberry, fireweed (Hovi & Korpela 2014) and bracken.

docs/method.md §(g): shoots (a stem with leaves along it) at random positions in the 6 x 6 m plot
until the plot reaches its LAI (raspberry 3.35, fireweed 2.0, from Kuusk et al. 2004), with a
small random LAI variation per instance; planophile leaves, uniform azimuths; leaf rho/tau
0.47/0.50, stem 0.47/0. The paper's own shoot regressions are UNSPECIFIED; the structure
here follows the docs/method.md suggestions, numbers in ``structure.csv``:

- **Shoot heights** uniform in [``shoot_height_min_frac`` h, h], the first shoot exactly h, so
  the plot top is the field height h.
- **Stem**: ``stem_segments`` prisms from the base to the apex at the shoot height, leaning
  by ``lean_frac`` of the height at the apex along a random azimuth (quadratic in height:
  raspberry canes arch, fireweed stands upright); diameter from ``stem_base_diameter_m`` to
  ``stem_top_diameter_m``.
- **Nodes**: ``nodes_per_shoot`` evenly along the leafy zone (from ``leafy_from`` of the
  height to the apex; internodes lengthen on taller shoots), successive nodes turned by
  ``divergence_deg``, ``leaves_per_node`` leaves per node (a pair is opposite).
- **Leaf size** along the leafy zone: relative x from 0 (lowest node) to 1 (apex), size
  linear from ``size_base_rel`` to 1 at ``size_peak_pos`` then to ``size_top_rel``, times
  ``leaf_area_cm2``.
- **Compound leaves** (raspberry): ``leaflets_lower`` leaflets below ``compound_split`` of the
  leafy zone, ``leaflets_upper`` above; terminal leaflet at the end of a petiole of
  ``petiole_m`` rising at ``petiole_elev_deg``, first lateral pair (area ``lateral_rel_1``) at
  the same point and the second pair (``lateral_rel_2``) halfway along the petiole, turned
  by +-``leaflet_spread_deg`` from the petiole azimuth.
- **Leaves** point away from the stem (the horizontal petiole direction projected on the
  leaf plane); normals from the LAD with uniform azimuths.
- **LAI**: every shoot carries the same leaf area; shoots are added until their leaf area
  reaches the target, then every leaf is scaled by target / realised (a factor within one
  shoot's share of 1), so the realised LAI equals the target.

Random shoot positions make the plot a Boolean model of shoots: its nadir gap fraction is
exp(-Omega G(0) L), where Omega <= 1 measures how much the leaves of one shoot hide each
other (the values over the Table 1 height ranges, checked by the tests: docs/validation.md,
"Vegetation models").

Positions are uniform (or a Thomas process of radius ``clumping`` with
``plants_per_cluster`` shoots per cluster) and periodic: leaf bases and stem segments are
wrapped into the plot (:mod:`waveforest.vegetation.placement`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from waveforest.vegetation.lad import LeafAngleDistribution, sample_normals
from waveforest.vegetation.leaves import load_outline, place_leaves
from waveforest.vegetation.params import SpeciesParams
from waveforest.vegetation.placement import positions, wrap
from waveforest.vegetation.plant import Plant, horizontal, piecewise_profile
from waveforest.vegetation.wood import prisms


def _layout(p: SpeciesParams, hs: np.ndarray):
    """Nodes and leaflets of shoots of heights ``hs`` (structure only, no randomness).

    Returns
    -------
    dict with node arrays (shoot index, relative position x, height z) and leaflet arrays
    (node index, leaf-in-node k, leaflet slot 0 terminal / 1 first pair / 2 second pair,
    side -1/0/+1, relative area), and the leaf area of each shoot, m^2.
    """
    lf = p["leafy_from"]
    n_nodes = np.full(hs.size, max(1, int(round(p["nodes_per_shoot"]))), dtype=np.int64)
    shoot = np.repeat(np.arange(hs.size), n_nodes)
    j = np.arange(shoot.size) - np.repeat(np.cumsum(n_nodes) - n_nodes, n_nodes)
    x = (j + 0.5) / n_nodes[shoot]
    z = hs[shoot] * (lf + (1.0 - lf) * x)
    size = piecewise_profile(x, p["size_base_rel"], p["size_peak_pos"], p["size_top_rel"])
    lpn = int(round(p["leaves_per_node"]))
    n_leaflets = np.where(x < p["compound_split"], int(p["leaflets_lower"]), int(p["leaflets_upper"]))
    # leaflet table: every leaf has a terminal; >= 3 adds pair 1; >= 5 adds pair 2
    slots = [(0, 0, 1.0, 1), (1, -1, p["lateral_rel_1"], 3), (1, 1, p["lateral_rel_1"], 3),
             (2, -1, p["lateral_rel_2"], 5), (2, 1, p["lateral_rel_2"], 5)]
    node_i, k_i, slot_i, side_i, rel_i = [], [], [], [], []
    nodes = np.arange(shoot.size)
    for k in range(lpn):
        for slot, side, rel, need in slots:
            sel = nodes[n_leaflets >= need]
            node_i.append(sel)
            k_i.append(np.full(sel.size, k))
            slot_i.append(np.full(sel.size, slot))
            side_i.append(np.full(sel.size, side))
            rel_i.append(np.full(sel.size, rel))
    node_i = np.concatenate(node_i)
    rel_area = np.concatenate(rel_i) * size[node_i] * p["leaf_area_cm2"] * 1e-4
    shoot_area = np.bincount(shoot[node_i], weights=rel_area, minlength=hs.size)
    return dict(shoot=shoot, j=j, x=x, z=z, node=node_i, k=np.concatenate(k_i),
                slot=np.concatenate(slot_i), side=np.concatenate(side_i), area=rel_area,
                shoot_area=shoot_area)


def build_shoots(p: SpeciesParams, height: float, rng: np.random.Generator,
                 lad: LeafAngleDistribution, leaf_area: float, leaf_area_scale: float,
                 clumping: float) -> Plant:
    """A plot of shoots of species ``p`` reaching the one-sided leaf area ``leaf_area`` (m^2).

    Parameters
    ----------
    p : SpeciesParams
        A ``shoots`` species.
    height : float, m
        Field (maximum) height of the sample.
    rng : numpy.random.Generator
    lad : LeafAngleDistribution
    leaf_area : float, m^2
        Target one-sided leaf area of the plot (LAI times the plot area).
    leaf_area_scale : float
        Factor on every leaf's area after the LAI is reached.
    clumping : float, m
        Thomas-process cluster radius (0 = uniform random positions).

    Returns
    -------
    Plant
    """
    h = float(height)
    # every shoot carries the same leaf area (a fixed number of nodes, sizes relative to the
    # leafy zone): shoots until the target is reached, then all leaves scaled to it exactly
    per_shoot = _layout(p, np.array([h]))["shoot_area"][0]
    n = max(1, int(np.ceil(leaf_area / per_shoot)))
    hs = rng.uniform(p["shoot_height_min_frac"] * h, h, n)
    hs[0] = h
    lay = _layout(p, hs)
    factor = leaf_area / lay["shoot_area"].sum()

    # shoot bases, lean and node azimuths
    base = positions(n, rng, clumping, p["plants_per_cluster"])
    lean_az = rng.uniform(0.0, 2.0 * math.pi, n)
    az0 = rng.uniform(0.0, 2.0 * math.pi, n)
    stems = _Stems(base, p["lean_frac"] * hs, horizontal(lean_az)[:, :2], hs)
    wood = _stem_wood(p, stems)
    leaves, areas, ln, width = _shoot_leaves(p, stems, lay, az0, factor, leaf_area_scale, lad, rng)
    return Plant(
        leaves=leaves,
        leaf_area_m2=float(areas.sum()),
        wood=wood,
        n_plants=n,
        element_size_m=float(np.hypot(ln.max(), width) + p["petiole_m"]),
    )


class _Stems(NamedTuple):
    """The stems of n shoots: ``base`` (n, 2) m, apex offset ``lean`` (n,) m along the
    horizontal unit vectors ``lean_dir`` (n, 2), heights ``hs`` (n,) m."""

    base: np.ndarray
    lean: np.ndarray
    lean_dir: np.ndarray
    hs: np.ndarray

    def point(self, shoot: np.ndarray, u: np.ndarray) -> np.ndarray:
        """(k, 3) points at relative height ``u`` (0 base, 1 apex) of stems ``shoot``; the
        lean grows with u^2."""
        xy = self.base[shoot] + (self.lean[shoot] * u * u)[:, None] * self.lean_dir[shoot]
        return np.concatenate([xy, (self.hs[shoot] * u)[:, None]], axis=1)


def _stem_wood(p: SpeciesParams, stems: _Stems) -> np.ndarray:
    """Triangles of ``stem_segments`` tapered prisms per stem, each segment wrapped into the
    plot by its midpoint."""
    n = len(stems.hs)
    k = int(round(p["stem_segments"]))
    u = np.linspace(0.0, 1.0, k + 1)
    sh = np.repeat(np.arange(n), k)
    uu = np.tile(u[:-1], n)
    p0, p1 = stems.point(sh, uu), stems.point(sh, uu + 1.0 / k)
    d = p["stem_base_diameter_m"] + (p["stem_top_diameter_m"] - p["stem_base_diameter_m"]) * u
    shift = np.zeros_like(p0)
    mid = 0.5 * (p0[:, :2] + p1[:, :2])
    shift[:, :2] = wrap(mid) - mid
    return prisms(p0 + shift, p1 + shift, np.tile(d[:-1], n), np.tile(d[1:], n))


def _shoot_leaves(p: SpeciesParams, stems: _Stems, lay: dict, az0: np.ndarray, factor: float,
                  leaf_area_scale: float, lad: LeafAngleDistribution,
                  rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The leaves of every node of :func:`_layout` ``lay``, their areas times ``factor`` (to the
    target LAI) and ``leaf_area_scale``.

    Leaf bases at the petiole's end (``petiole_m`` at ``petiole_elev_deg``; the second
    lateral pair halfway), wrapped into the plot; node azimuths from ``az0`` turned by
    ``divergence_deg``, pairs opposite; leaflets spread by ``leaflet_spread_deg``; normals
    from the LAD. Returns the triangles, the (k,) areas, m^2, the (k,) leaf lengths, m, and
    the widest leaf's width, m.
    """
    shoot, node = lay["shoot"], lay["node"]
    node_pos = stems.point(shoot, lay["z"] / stems.hs[shoot])
    node_az = az0[shoot] + lay["j"] * math.radians(p["divergence_deg"])
    psi = node_az[node] + lay["k"] * math.pi  # leaf azimuth (pairs opposite)
    elev = math.radians(p["petiole_elev_deg"])
    pdir = np.stack([math.cos(elev) * np.cos(psi), math.cos(elev) * np.sin(psi),
                     np.full(psi.size, math.sin(elev))], axis=1)
    along = np.where(lay["slot"] == 2, 0.5, 1.0) * p["petiole_m"]
    leaf_base = node_pos[node] + along[:, None] * pdir
    toward = horizontal(psi + lay["side"] * math.radians(p["leaflet_spread_deg"]))
    areas = lay["area"] * factor * leaf_area_scale
    outline = load_outline(p.element)
    wf = outline.width_factor(p["leaf_length_width"])
    ln = outline.length_for_area(areas, wf)
    leaf_base[:, :2] = wrap(leaf_base[:, :2])
    normals = sample_normals(lad, areas.size, rng)
    leaves = place_leaves(outline, leaf_base, normals, toward, ln, wf)
    return leaves, areas, ln, float(ln.max()) * wf * outline.width
