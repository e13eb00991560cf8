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
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd
import pyarrow as pa

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
    height = s["height_m"].to_numpy(float)
    comparison = compared[idx[keep]] & ~below
    ground_z = s["ground_z"].to_numpy(float)
    columns = {
        "sample_id": pa.array(s["sample_id"].astype(str).to_list(), pa.string()),
        "species": pa.array(s["species"].astype(str).to_list(), pa.string()),
        "functional_group": pa.array(s["functional_group"].astype(str).to_list(), pa.string()),
        "ground_z": pa.array(ground_z, pa.float64()),
        "sample_x": pa.array(s["x"].to_numpy(float), pa.float64()),
        "sample_y": pa.array(s["y"].to_numpy(float), pa.float64()),
        "height_m": pa.array(height, pa.float64()),
        "is_tree": pa.array(s["is_tree"].to_numpy(bool), pa.bool_()),
        "sample_distance_m": pa.array(dist[keep], pa.float64()),
        "first_echo_h_m": pa.array(echo[keep, 2] - ground_z, pa.float64()),
        "single_echo_set": pa.array(single, pa.bool_()),
        "classification_set": pa.array(classification, pa.bool_()),
        "comparison_set": pa.array(comparison, pa.bool_()),
        "below_crown_set": pa.array(below, pa.bool_()),
    }
    for name in SELECT_COLUMNS:
        if name in out.column_names:
            out = out.drop_columns([name])
        out = out.append_column(name, columns[name])
    return out


def dataset_of(pulses: pa.Table, source: str = "<pulses>") -> str:
    """The one dataset name of a pulse table."""
    names = pulses.column("dataset").unique().to_pylist()
    if len(names) != 1:
        raise WaveforestError(f"{source}: expected pulses of one dataset, found {names or 'none'}")
    return str(names[0])
