"""Select the pulses that hit field samples (docs/method.md §(i1), i4).

A pulse belongs to a field sample of the dataset's year when its first DR echo
``(echo_x[0], echo_y[0])`` lies within the sample's selection radius of the sample position:

* trees (``is_tree``): ``tree_radius_m`` (0.5 m) around the tree base, and the first echo
  must lie at least ``tree_min_echo_h_m`` (1 m) above the sample's ground elevation
  (lower echoes are ground vegetation, not the tree);
* low vegetation and ground samples: the sample's own ``radius_m`` (0.5 m S10, 1.0 m S12).

When several samples qualify, the nearest one (horizontal distance) wins. The search is a
KD-tree query over all pulses at once (no loop over pulses).

Flags mark the subsets the later stages use:

* ``single_echo_set`` (docs/method.md §(i4)): pulses with exactly one DR echo (not in
  ``below_crown_set``): the per-pulse part of the classification rule;
* ``classification_set`` (docs/method.md §(i4)): ``single_echo_set`` pulses of species with at
  least ``min_pulses`` such pulses in this dataset: Table 1's rule applied to this dataset
  alone. ``classify``, given every dataset's selection, applies the rule as Table 1 states it
  (at least ``min_pulses`` in at least one dataset) from ``single_echo_set``;
* ``comparison_set`` (docs/method.md §(i1)): pulses of the modelled species (``simulate.species``), for
  species with a height window (birch: trees of 2.5-5 m) only samples inside it;
* ``below_crown_set`` (beyond the paper, for ``diagnose``): pulses whose first echo lies
  within ``tree_radius_m`` of a comparison tree but lower than ``tree_min_echo_h_m``: the
  ground or ground vegetation under the crown, seen through a gap in it. They are assigned
  to that tree only when no sample takes them by the rules above, and are in neither other
  set, so the paper's analyses do not see them.

:func:`ring_pulses` (beyond the paper, for ``diagnose``, not part of ``select``'s table) finds
the pulses that no sample takes whose beam meets the ground in a ring around a comparison tree:
a rule on the beam's geometry, not on what it hit, so that a simulated twin can follow it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc

from waveforest.errors import WaveforestError
from waveforest.io.pulses import list_to_padded

SELECT_COLUMNS = (
    "sample_id", "species", "functional_group", "ground_z", "sample_x", "sample_y",
    "height_m", "is_tree", "sample_distance_m", "first_echo_h_m",
    "single_echo_set", "classification_set", "comparison_set", "below_crown_set",
)
"""Columns that :func:`select_pulses` appends to the pulse table: sample_id, species,
functional_group, ground_z (m), sample_x/_y (m), height_m (field max height, m), is_tree,
sample_distance_m (first echo to sample, horizontal, m), first_echo_h_m (first echo above
ground_z, m) and the four flags of the module docstring."""

_FIRST_K = 8
"""Nearest samples examined first per pulse; doubled until no candidate can be missed."""


@dataclass(frozen=True)
class SelectRules:
    """The selection rules (config sections ``select`` and ``simulate``; built by
    :func:`waveforest.settings.select_rules`, defaults equal to the schema's)."""

    tree_radius_m: float = 0.5
    tree_min_echo_h_m: float = 1.0
    min_pulses: int = 30
    comparison_species: tuple[str, ...] = ("birch", "raspberry", "fireweed")
    height_range_m: dict = field(default_factory=lambda: {"birch": (2.5, 5.0)})


def first_echoes(pulses: pa.Table) -> np.ndarray:
    """(n, 3) float64 position of each pulse's first DR echo, m; NaN for pulses without one."""
    out = np.full((pulses.num_rows, 3), np.nan)
    for j, name in enumerate(("echo_x", "echo_y", "echo_z")):
        values, lengths = list_to_padded(pulses.column(name), dtype=np.float64)
        has = lengths > 0
        if values.shape[1]:
            out[has, j] = values[has, 0]
    return out


def match_samples(echo_xyz: np.ndarray, fields: pd.DataFrame, rules: SelectRules, *,
                  below_crown: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Index of the field sample each first echo belongs to (-1: none) and the distance.

    Parameters
    ----------
    echo_xyz : (n, 3) float64, m
        First-echo positions (NaN rows never match).
    fields : DataFrame
        Field samples (columns x, y, ground_z, radius_m, is_tree).
    rules : SelectRules
    below_crown : bool
        Match instead the echoes that lie within ``tree_radius_m`` of a tree but lower than
        ``tree_min_echo_h_m`` above its ground (those the tree rule leaves out).

    Returns
    -------
    index : (n,) int64
        Row of ``fields`` (positional), or -1.
    distance : (n,) float64, m
        Horizontal distance to that sample (NaN when -1).
    """
    n = echo_xyz.shape[0]
    index = np.full(n, -1, dtype=np.int64)
    distance = np.full(n, np.nan)
    n_f = len(fields)
    ok_rows = np.all(np.isfinite(echo_xyz), axis=1)
    if n_f == 0 or not ok_rows.any():
        return index, distance
    is_tree = fields["is_tree"].to_numpy(bool)
    radius = np.where(is_tree, rules.tree_radius_m, fields["radius_m"].to_numpy(float))
    ground = fields["ground_z"].to_numpy(float)
    from scipy.spatial import cKDTree

    tree = cKDTree(fields[["x", "y"]].to_numpy(float))
    xy = echo_xyz[ok_rows, :2]
    z = echo_xyz[ok_rows, 2]
    k = min(_FIRST_K, n_f)
    while True:
        d, i = tree.query(xy, k=k, distance_upper_bound=float(radius.max()))
        d, i = d.reshape(len(xy), k), i.reshape(len(xy), k)
        if k == n_f or not np.isfinite(d[:, -1]).any():
            break  # every sample within the largest radius has been seen
        k = min(2 * k, n_f)
    found = np.isfinite(d)
    ii = np.where(found, i, 0)
    valid = found & (d <= radius[ii])
    low = is_tree[ii] & (z[:, None] - ground[ii] < rules.tree_min_echo_h_m)
    valid &= low if below_crown else ~low
    first = np.argmax(valid, axis=1)
    hit = valid[np.arange(len(xy)), first]
    sub_index = np.where(hit, ii[np.arange(len(xy)), first], -1)
    sub_dist = np.where(hit, d[np.arange(len(xy)), first], np.nan)
    index[ok_rows] = sub_index
    distance[ok_rows] = sub_dist
    return index, distance


def beam_ground_points(pulses: pa.Table, z) -> np.ndarray:
    """(n, 2) float64: where each pulse's beam line (sensor + s dir) crosses the height ``z``
    (m; scalar or (n,)), x and y in m."""
    c = {k: pulses.column(k).to_numpy(zero_copy_only=False).astype(np.float64)
         for k in ("sensor_x", "sensor_y", "sensor_z", "dir_x", "dir_y", "dir_z")}
    s = (np.asarray(z, np.float64) - c["sensor_z"]) / c["dir_z"]
    return np.column_stack([c["sensor_x"] + c["dir_x"] * s, c["sensor_y"] + c["dir_y"] * s])


def match_rings(pulses: pa.Table, trees: pd.DataFrame, inner_m: float, outer_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The tree whose ring each beam meets: the ground point of the beam (its line at the tree's
    ``ground_z``) lies at least ``inner_m`` and less than ``outer_m`` from the tree base; the
    nearest such tree wins. A rule on the beam alone, not on what it hit.

    Parameters
    ----------
    pulses : pa.Table
        Pulse rows (sensor_x/_y/_z, dir_x/_y/_z).
    trees : DataFrame
        Candidate trees (columns x, y, ground_z).
    inner_m, outer_m : float
        The ring's radii, m.

    Returns
    -------
    index : (n,) int64
        Row of ``trees`` (positional), or -1.
    distance : (n,) float64, m
        Horizontal distance of the ground point from that base (NaN when -1).
    """
    n = pulses.num_rows
    index, distance = np.full(n, -1, dtype=np.int64), np.full(n, np.nan)
    if n == 0 or len(trees) == 0:
        return index, distance
    from scipy.spatial import cKDTree

    base = trees[["x", "y"]].to_numpy(np.float64)
    ground = trees["ground_z"].to_numpy(np.float64)
    z_ref = float(np.median(ground))
    at_ref = beam_ground_points(pulses, z_ref)
    sensor, d = (np.column_stack([pulses.column(f"{what}_{axis}").to_numpy(zero_copy_only=False).astype(np.float64)
                                  for axis in "xyz"]) for what in ("sensor", "dir"))
    ok = np.all(np.isfinite(at_ref), axis=1) & (np.abs(d[:, 2]) > 0)
    if not ok.any():
        return index, distance
    # a beam's ground point moves by |dz| tan(zenith) between z_ref and a tree's own ground
    slack = float(np.max(np.abs(ground - z_ref))) * float(np.max(np.hypot(d[ok, 0], d[ok, 1]) / np.abs(d[ok, 2])))
    tree = cKDTree(base)
    k = min(_FIRST_K, len(trees))
    while True:
        dist, i = tree.query(at_ref[ok], k=k, distance_upper_bound=outer_m + slack)
        dist, i = dist.reshape(-1, k), i.reshape(-1, k)
        if k == len(trees) or not np.isfinite(dist[:, -1]).any():
            break  # every tree that can reach the ring has been seen
        k = min(2 * k, len(trees))
    found = np.isfinite(dist)
    ii = np.where(found, i, 0)
    s, e = sensor[ok], d[ok]
    t = (ground[ii] - s[:, 2:3]) / e[:, 2:3]  # (m, k): the beam at each candidate's ground
    r = np.hypot(s[:, 0:1] + e[:, 0:1] * t - base[ii, 0], s[:, 1:2] + e[:, 1:2] * t - base[ii, 1])
    r = np.where(found & (r >= inner_m) & (r < outer_m), r, np.inf)
    best = np.argmin(r, axis=1)
    rows = np.arange(len(r))
    hit = np.isfinite(r[rows, best])
    index[ok] = np.where(hit, ii[rows, best], -1)
    distance[ok] = np.where(hit, r[rows, best], np.nan)
    return index, distance


def comparison_samples(fields: pd.DataFrame, rules: SelectRules) -> np.ndarray:
    """(J,) bool: which field samples are compared with simulations (modelled species, in
    their height window)."""
    species = fields["species"].to_numpy(object)
    height = fields["height_m"].to_numpy(float)
    out = np.isin(species, np.array(rules.comparison_species, dtype=object))
    for sp, (lo, hi) in rules.height_range_m.items():
        out &= (species != sp) | ((height >= lo) & (height <= hi))
    return out


def select_pulses(pulses: pa.Table, fields: pd.DataFrame, year: int, rules: SelectRules) -> pa.Table:
    """The pulses of ``pulses`` that hit a field sample of ``year``, with the sample columns.

    Parameters
    ----------
    pulses : pa.Table
        Pulse table (waveforest.io.pulses.PULSE_SCHEMA) of one dataset.
    fields : DataFrame
        ``fields.csv`` (all years; only ``year`` is used).
    year : int
        The dataset's campaign year.
    rules : SelectRules

    Returns
    -------
    pa.Table
        The selected rows in their input order, plus the columns :data:`SELECT_COLUMNS`.
    """
    f = fields[fields["year"] == year].reset_index(drop=True)
    echo = first_echoes(pulses)
    idx, dist = match_samples(echo, f, rules)
    under, under_dist = match_samples(echo, f, rules, below_crown=True)
    compared = comparison_samples(f, rules)
    below = (idx < 0) & (under >= 0)
    below[below] = compared[under[below]]
    idx = np.where(below, under, idx)
    dist = np.where(below, under_dist, dist)
    keep = np.flatnonzero(idx >= 0)
    below = below[keep]
    out = pulses.take(pa.array(keep, type=pa.int64()))
    s = f.iloc[idx[keep]].reset_index(drop=True)
    species = s["species"].to_numpy(object)
    n_echoes = out.column("n_echoes").to_numpy(zero_copy_only=False).astype(np.int64)
    single = (n_echoes == 1) & ~below
    counts = pd.Series(species[single]).value_counts()
    frequent = np.isin(species, counts.index[counts >= rules.min_pulses].to_numpy(object))
    classification = single & frequent
    comparison = compared[idx[keep]] & ~below
    flags = {"single_echo_set": single, "classification_set": classification, "comparison_set": comparison,
             "below_crown_set": below}
    return with_select_columns(out, s, dist[keep], echo[keep, 2], flags)


def with_select_columns(pulses: pa.Table, samples: pd.DataFrame, distance: np.ndarray, first_echo_z: np.ndarray,
                        flags: dict) -> pa.Table:
    """``pulses`` with the columns :data:`SELECT_COLUMNS` (replaced where present): the field
    sample of each row (``samples``, one fields.csv row per pulse), its ``distance`` (m), the
    first echo's height above the sample's ground (from ``first_echo_z``, m) and the four
    flags (name -> (n,) bool)."""
    ground_z = samples["ground_z"].to_numpy(float)
    columns = {
        "sample_id": pa.array(samples["sample_id"].astype(str).to_list(), pa.string()),
        "species": pa.array(samples["species"].astype(str).to_list(), pa.string()),
        "functional_group": pa.array(samples["functional_group"].astype(str).to_list(), pa.string()),
        "ground_z": pa.array(ground_z, pa.float64()),
        "sample_x": pa.array(samples["x"].to_numpy(float), pa.float64()),
        "sample_y": pa.array(samples["y"].to_numpy(float), pa.float64()),
        "height_m": pa.array(samples["height_m"].to_numpy(float), pa.float64()),
        "is_tree": pa.array(samples["is_tree"].to_numpy(bool), pa.bool_()),
        "sample_distance_m": pa.array(distance, pa.float64()),
        "first_echo_h_m": pa.array(np.asarray(first_echo_z, float) - ground_z, pa.float64()),
        **{name: pa.array(np.asarray(flags[name], bool), pa.bool_()) for name in SELECT_COLUMNS[-4:]},
    }
    for name in SELECT_COLUMNS:
        if name in pulses.column_names:
            pulses = pulses.drop_columns([name])
        pulses = pulses.append_column(name, columns[name])
    return pulses


def ring_pulses(pulses: pa.Table, fields: pd.DataFrame, year: int, rules: SelectRules, outer_m: float) -> pa.Table:
    """The pulses of ``pulses`` whose beam meets the ground in the ring of a comparison tree of
    ``year`` (:func:`match_rings`, from ``rules.tree_radius_m`` to ``outer_m``) and that no sample
    takes (:func:`select_pulses`, the stratum under the crowns included), with the columns
    :data:`SELECT_COLUMNS` (every flag False; ``sample_distance_m`` the ground point's distance
    from the base) and ``ring_set`` True. Beyond the paper (diagnose's stratum "ring")."""
    f = fields[fields["year"] == year].reset_index(drop=True)
    trees = f[comparison_samples(f, rules) & f["is_tree"].to_numpy(bool)].reset_index(drop=True)
    taken = select_pulses(pulses, fields, year, rules).column("pulse_id")
    free = pulses.filter(pc.invert(pc.is_in(pulses.column("pulse_id"), value_set=taken)))
    idx, dist = match_rings(free, trees, float(rules.tree_radius_m), float(outer_m))
    keep = np.flatnonzero(idx >= 0)
    out = free.take(pa.array(keep, type=pa.int64()))
    n = len(keep)
    no = np.zeros(n, bool)
    out = with_select_columns(out, trees.iloc[idx[keep]].reset_index(drop=True), dist[keep],
                              first_echoes(out)[:, 2], dict.fromkeys(SELECT_COLUMNS[-4:], no))
    return out.append_column("ring_set", pa.array(np.ones(n, bool)))


def dataset_of(pulses: pa.Table, source: str = "<pulses>") -> str:
    """The one dataset name of a pulse table."""
    names = pulses.column("dataset").unique().to_pylist()
    if len(names) != 1:
        raise WaveforestError(f"{source}: expected pulses of one dataset, found {names or 'none'}")
    return str(names[0])
