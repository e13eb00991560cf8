"""The populations compared: pulse keys, selection rules and the strata.

docs/method.md §(j) (the simulator and the strata). A pulse of the diagnosis is a row of
``select``'s ``comparison_set`` of a modelled species (``stratum`` ""); a tree's pulse whose
first echo lies within ``diagnose.near_stem_m`` of the stem (``sample_distance_m``) is in the
stratum :data:`NEAR_STEM`, where that species has enough field samples on both sides of the split
(:data:`NEAR_STEM_MIN_SAMPLES`); with ``diagnose.below_crown``, a pulse of the stratum under the
crowns (``stratum`` :data:`BELOW_CROWN`): one whose own first CFD echo lies within
``select.tree_radius_m`` of a compared stem and lower than ``select.tree_min_echo_h_m`` (the
ground seen through gaps in the crown); with ``diagnose.ring_m``, a pulse of the stratum
:data:`RING`: one that no sample takes whose beam meets the ground in the ring between
``select.tree_radius_m`` and ``diagnose.ring_m`` of a compared stem, and whose first echo lies
lower than ``select.tree_min_echo_h_m`` (the ground beside the tree). The stratum near the stem
splits cells only: it is assigned after the caps, so it changes neither the pulses simulated nor
the field samples resampled (the strata under the crowns and beside the trees add pulses, capped
on their own).
Real and simulated pulses of a stratum are drawn by one rule and one detector:

* real side: :func:`own_cfd_echoes` gives every pulse the CFD echoes a twin would get, and
  :func:`with_pulses_under_crowns` re-draws ``below_crown_set`` with ``select``'s rules on
  them; :func:`with_ring_pulses` adds the ring's pulses, chosen by their beams;
  :func:`added_features` computes the features of both;
* twin side (:class:`.twins.StudySimulator`): up to :data:`BELOW_CROWN_ATTEMPTS` traces
  of the beam, turned about the stem (:func:`turned_about_stems`, :func:`stem_distance`),
  the first whose echo meets the same rule;
  a twin of the ring whose own first echo lies within ``select.tree_radius_m`` of the stem is
  dropped (a sample would have taken its real pulse);
* both sides: :func:`apply_rules` (``select``'s and ``compare``'s rules, docs/method.md §(i1),
  and the strata's height rule).

:func:`pulse_keys` lists the pulses (with a seeded, order-independent cap for the fit
subset); :func:`real_features` joins their real features. Lengths in m, times in ns.
Errors: :class:`waveforest.errors.WaveforestError` for select tables without the key
columns and for no matching real feature row.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc

from waveforest.constants import RANGE_PER_NS
from waveforest.diagnose.gap import MIN_CELL_SAMPLES
from waveforest.errors import WaveforestError
from waveforest.io.pulses import list_to_padded, padded_to_list
from waveforest.model.forward import SensorSettings, twin_echoes
from waveforest.model.selection import SelectRules, beam_ground_points, ring_pulses, select_pulses
from waveforest.rng import hash_ids, stable_hash
from waveforest.sensor import feature_table
from waveforest.sensor.agc import GAIN_COLUMN
from waveforest.sensor.checks import gain_or_one

BELOW_CROWN = "below crown"
"""``stratum`` of the pulses of ``select``'s ``below_crown_set`` (the others have "")."""

RING = "ground beside"
"""``stratum`` of the pulses of :func:`with_ring_pulses` (``diagnose.ring_m``): those whose first
echo lies lower than ``select.tree_min_echo_h_m`` (:func:`apply_rules`), the ground and what grows
on it beside the tree."""

RING_BLANKED = ("H", "Npeaks", "FWHM")
"""First-echo features the stratum :data:`RING` does not compare (NaN on both sides, after the
height rule): a ground return's height and width are the ground's and the system pulse's, and
their spread comes from rare low echoes whose heavy tails carried most of the stratum's noise
floor; what grows on the ground shows in the return's strength, Apeak and E
(docs/validation.md, Diagnose: the ground beside the trees)."""

ADDED_STRATA = (BELOW_CROWN, RING)
"""Strata of pulses that ``select``'s comparison set does not hold; their real features come
from their rows in the diagnosis's tables (:func:`added_features`)."""

NEAR_STEM = "near stem"
"""``stratum`` of the comparison pulses of trees within ``diagnose.near_stem_m`` of the stem."""

NEAR_STEM_MIN_SAMPLES = 10
"""A dataset's tree species is split at the stem only where both parts hold at least this many
field samples: the intervals resample field samples, and cells of a few give the bootstrap a
long tail (docs/validation.md, Near the stem)."""

BELOW_CROWN_ATTEMPTS = 16
"""Most attempts at a twin under the crown per pulse of that stratum (:class:`.twins.StudySimulator`)."""

WAVEFORM_FEATURES = ("Npeaks", "Apeak", "FWHM", "E")
"""Features restricted by ``simulate.compare_min_h_m`` (all but H)."""

KEY_COLUMNS = ("dataset", "pulse_id", "gps_time", "sample_id", "species", "is_tree", "comparison_set",
               "below_crown_set", "ring_set", "sample_distance_m")
"""``select`` columns that identify a pulse to simulate."""


@dataclass(frozen=True)
class StrataSettings:
    """The populations compared and the rules that draw them (config sections ``select``,
    ``simulate``, ``diagnose``, ``sensor``, ``seed``).

    Attributes
    ----------
    rules : SelectRules
        ``select``'s rules; ``comparison_species`` are the modelled species compared.
    compare_min_h_m : mapping species -> m
        ``compare``'s rule (``simulate.compare_min_h_m``).
    near_stem_m : float or None, m
        ``diagnose.near_stem_m``.
    below_crown : bool
        ``diagnose.below_crown``.
    ring_m : float or None, m
        ``diagnose.ring_m``: outer radius of the ring around a compared tree's base (None: no ring).
    pulses_per_species : int or None
        ``diagnose.pulses_per_species``: the budget shared by the diagnosed datasets.
    seed : int
        The study's master seed (the seeded caps).
    sensor : SensorSettings
        The sensor model: the features, and the CFD of a calibration without its own.
    """

    rules: SelectRules
    compare_min_h_m: Mapping[str, float]
    near_stem_m: float | None
    below_crown: bool
    pulses_per_species: int | None
    seed: int
    sensor: SensorSettings
    ring_m: float | None = None


def apply_rules(features: pd.DataFrame, strata: StrataSettings) -> pd.DataFrame:
    """The selection rules of ``select`` and ``compare`` applied to a feature table.

    Rows of trees (``is_tree``) whose first echo lies below ``select.tree_min_echo_h_m`` are
    dropped (``select``'s rule, which the real pulses satisfy by construction), and so are
    rows of the strata "below crown" and :data:`RING` whose first echo lies at or above it (the
    rule of those strata, on both sides), and the features :data:`RING_BLANKED` of the ring's
    rows become NaN; for species in ``simulate.compare_min_h_m`` the
    waveform features of the rows outside those strata with H at or below the threshold become
    NaN (``compare``'s rule, docs/method.md §(i1)). Rows without a first echo (H NaN) are
    dropped.

    Parameters
    ----------
    features : DataFrame
        Feature table with species, H, the waveform features and optionally is_tree and
        stratum.
    strata : StrataSettings
    """
    df = features[np.isfinite(features["H"].to_numpy(dtype=float))].copy()
    stratum = df["stratum"].astype(str).to_numpy() if "stratum" in df else np.full(len(df), "")
    added = np.isin(stratum, ADDED_STRATA)
    if "is_tree" in df.columns:
        tree = df["is_tree"].fillna(False).astype(bool).to_numpy()
        high = df["H"].to_numpy(float) >= float(strata.rules.tree_min_echo_h_m)
        keep = np.where(added, ~high, ~tree | high)
        df, stratum, added = df[keep].copy(), stratum[keep], added[keep]
    df.loc[stratum == RING, [f for f in RING_BLANKED if f in df.columns]] = np.nan
    species = df["species"].astype(str).to_numpy()
    h = df["H"].to_numpy(float)
    for sp, lo in strata.compare_min_h_m.items():
        low = (species == sp) & ~(h > float(lo)) & ~added
        for f in WAVEFORM_FEATURES:
            if f in df.columns:
                df.loc[low, f] = np.nan
    return df.reset_index(drop=True)


def turned_about_stems(pulses: pa.Table, azimuth) -> pa.Table:
    """``pulses`` with each beam turned about its sample's vertical axis by ``azimuth`` (rad):
    the sensor position and anchor about (sample_x, sample_y), the direction with them.
    Heights, ranges and each point's distance from the stem are kept (echo lists are not
    turned; the simulation does not read them)."""
    c, s = np.cos(np.asarray(azimuth, float)), np.sin(np.asarray(azimuth, float))
    x0, y0 = (pulses.column(k).to_numpy(zero_copy_only=False).astype(float) for k in ("sample_x", "sample_y"))
    out = pulses
    for x, y, origin in (("sensor_x", "sensor_y", (x0, y0)), ("anchor_x", "anchor_y", (x0, y0)),
                         ("dir_x", "dir_y", (0.0, 0.0))):
        u = out.column(x).to_numpy(zero_copy_only=False).astype(float) - origin[0]
        v = out.column(y).to_numpy(zero_copy_only=False).astype(float) - origin[1]
        out = out.set_column(out.schema.get_field_index(x), x, pa.array(origin[0] + c * u - s * v))
        out = out.set_column(out.schema.get_field_index(y), y, pa.array(origin[1] + s * u + c * v))
    return out


def stem_distance(pulses: pa.Table, z) -> np.ndarray:
    """Horizontal distance (m) from (sample_x, sample_y) of the point at height ``z`` (m) on
    each pulse's recorded beam line (sensor + s dir)."""
    at = beam_ground_points(pulses, z)
    return np.hypot(*(at[:, j] - pulses.column(c).to_numpy(zero_copy_only=False).astype(float)
                      for j, c in enumerate(("sample_x", "sample_y"))))


def own_cfd_echoes(pulses: pa.Table, calibration, sensor: SensorSettings) -> pa.Table:
    """``pulses`` with their DR echoes replaced by the CFD echoes of their own waveforms.

    The CFD, its range correction and its arming on the recorded noise (noise SD / AGC gain)
    are those that give a simulated twin its echoes (:func:`waveforest.model.forward.twin_echoes`);
    times, amplitudes and positions (on the recorded beam line, anchor + dir t c/2, as a
    twin's) replace the DR's. A pulse without a CFD echo is left out, as a twin without one is.

    Parameters
    ----------
    pulses : pa.Table
        AGC-normalised pulse rows of one dataset (``agc`` or ``select`` table rows).
    calibration : waveforest.sensor.calibration.Calibration
        The dataset's calibration (CFD, range correction, noise).
    sensor : SensorSettings
        Its CFD when the calibration has none.
    """

    samples, lengths = list_to_padded(pulses.column("samples"))
    sampling = pulses.column("sampling_ns").to_numpy(zero_copy_only=False)
    gain = gain_or_one(pulses.column(GAIN_COLUMN).to_numpy(zero_copy_only=False)) if GAIN_COLUMN in \
        pulses.column_names else None
    setup = sensor.setup(calibration.system, calibration.noise_mean, calibration.noise_sd,
                         float(sampling[0]) if len(sampling) else 1.0, range_correction=calibration.range_correction,
                         cfd=calibration.cfd)
    echoes = twin_echoes(samples, lengths, sampling, setup, gain)
    times, counts = np.nan_to_num(echoes.times_ns), echoes.n_echoes.astype(np.int64)
    columns = {"echo_time_ns": padded_to_list(times, counts, pa.float64()),
               "echo_intensity": padded_to_list(np.nan_to_num(echoes.amplitudes).astype(np.float32), counts,
                                                pa.float32()),
               "n_echoes": pa.array(counts.astype(np.int16))}
    for axis in "xyz":
        anchor = pulses.column(f"anchor_{axis}").to_numpy(zero_copy_only=False).astype(float)
        direction = pulses.column(f"dir_{axis}").to_numpy(zero_copy_only=False).astype(float)
        columns[f"echo_{axis}"] = padded_to_list(anchor[:, None] + direction[:, None] * times * RANGE_PER_NS,
                                                 counts, pa.float64())
    out = pulses
    for name, values in columns.items():
        out = out.set_column(out.schema.get_field_index(name), name, values)
    return out.filter(pa.array(counts > 0))


def _whole_samples(df: pd.DataFrame, cap: int, seed: int) -> pd.DataFrame:
    """Rows of whole field samples, in a seeded order of the samples (the same in every dataset),
    per species x stratum, while their pulses number at most ``cap``, and at least the first
    :data:`~waveforest.diagnose.gap.MIN_CELL_SAMPLES` (a cell of fewer is not compared: a cap that
    left one sample would drop the cell). A smaller cap keeps a subset of a larger one's samples.

    The order is the SplitMix64 mix (:func:`~waveforest.rng.hash_ids`) of each id's CRC under a
    key of ``seed``, so that each seed draws an independent subset. A CRC-32 of seed and id is
    affine in the id's bits: the orders of two seeds would be XOR-translates of one another
    (docs/validation.md, Diagnose: the noise floor)."""
    codes, uniq = pd.factorize(df["sample_id"].astype(str))
    ids = np.array([stable_hash(u) for u in uniq], np.int64)
    rank = hash_ids(stable_hash(seed, "diagnose sample"), ids)[codes]
    df = df.assign(_rank=rank).sort_values(["_rank", "sample_id", "pulse_id"])
    size = df.groupby(["species", "stratum", "sample_id"], sort=False)["pulse_id"].transform("size")
    first = ~df.duplicated(["species", "stratum", "sample_id"])
    cell = [df["species"], df["stratum"]]
    total = (size * first).groupby(cell, sort=False).cumsum()
    ordinal = first.astype(int).groupby(cell, sort=False).cumsum()  # 1 for a cell's first sample
    keep_sample = (total <= cap) | (ordinal <= MIN_CELL_SAMPLES)
    keep = keep_sample.where(first).groupby([df["species"], df["stratum"], df["sample_id"]], sort=False).transform("first")
    return df[keep.astype(bool)].drop(columns="_rank")


def dataset_share(budget: int | None, datasets: int) -> int | None:
    """Pulses per species of each of ``datasets`` diagnosed datasets under the budget
    ``diagnose.pulses_per_species`` (None = all): the budget over the datasets, rounded up."""
    return None if budget is None else -(-int(budget) // max(1, int(datasets)))


def pulse_keys(selected: dict, strata: StrataSettings, cap: int | None = None) -> pd.DataFrame:
    """The pulses the diagnosis simulates (module docstring).

    Parameters
    ----------
    selected : dict
        Dataset -> ``select`` pa.Table.
    strata : StrataSettings
    cap : int, optional
        At most this many pulses per dataset x species x stratum (a seeded random subset: a
        smaller cap gives a subset of a larger one); None = all. Applied after
        ``diagnose.pulses_per_species`` (whole field samples, :func:`_whole_samples`, up to
        each dataset's :func:`dataset_share` of the budget).

    Returns
    -------
    DataFrame
        dataset, pulse_id, gps_time (NaN where the table has none), sample_id, species, is_tree,
        stratum (:data:`BELOW_CROWN`, :data:`RING`, :data:`NEAR_STEM` or ""); sorted by dataset
        and pulse_id.
    """

    species = [str(s) for s in strata.rules.comparison_species]
    near_m = strata.near_stem_m
    optional = ("gps_time", "is_tree", "below_crown_set", "ring_set", "sample_distance_m")  # absent from other tools' tables
    parts = []
    share = dataset_share(strata.pulses_per_species, len(selected))
    for ds, table in sorted(selected.items()):
        missing = [c for c in KEY_COLUMNS if c not in table.column_names and c not in optional]
        if missing:
            raise WaveforestError(f"select table of {ds} lacks column(s) {', '.join(missing)}")
        df = table.select([c for c in KEY_COLUMNS if c in table.column_names]).to_pandas()
        df = df.reindex(columns=list(KEY_COLUMNS), fill_value=False)
        for col in ("gps_time", "sample_distance_m"):
            if col not in table.column_names:
                df[col] = np.nan
        below = df["below_crown_set"].fillna(False).astype(bool) & bool(strata.below_crown)
        ring = df["ring_set"].fillna(False).astype(bool) & (strata.ring_m is not None)
        df = df[(df["comparison_set"].fillna(False).astype(bool) | below | ring)
                & df["species"].astype(str).isin(species)]
        df = df.assign(stratum=np.select([below[df.index], ring[df.index]], [BELOW_CROWN, RING], "")).drop(
            columns=["comparison_set", "below_crown_set", "ring_set"])
        if share is not None:
            df = _whole_samples(df, share, int(strata.seed))
        # which species to split at the stem: decided before the fit cap, so fits and tests share cells
        split = [] if near_m is None else _split_species(df, float(near_m))
        if cap is not None:
            rank = hash_ids(stable_hash(int(strata.seed), ds, "diagnose"), df["pulse_id"].to_numpy(np.int64))
            df = df.assign(_rank=rank).sort_values(["_rank", "pulse_id"])
            df = df.groupby(["species", "stratum"], sort=False).head(int(cap)).drop(columns="_rank")
        if near_m is not None:  # after the caps: a split of cells, not a choice of pulses
            near = _tree(df) & _near(df, float(near_m)) & df["species"].isin(split)
            df["stratum"] = df["stratum"].where(~near, NEAR_STEM)
        parts.append(df.drop(columns="sample_distance_m"))
    keys = pd.concat(parts, ignore_index=True) if parts else pd.DataFrame(
        columns=["dataset", "pulse_id", "gps_time", "sample_id", "species", "is_tree", "stratum"])
    keys["sample_id"] = keys["sample_id"].astype(str)
    keys["species"] = keys["species"].astype(str)
    keys["dataset"] = keys["dataset"].astype(str)
    return keys.sort_values(["dataset", "pulse_id"]).reset_index(drop=True)


def _tree(df: pd.DataFrame) -> pd.Series:
    """Tree comparison pulses (not under the crowns) of keys."""
    return (df["stratum"] == "") & df["is_tree"].fillna(False).astype(bool)


def _near(df: pd.DataFrame, near_m: float) -> np.ndarray:
    """Pulses of keys whose first echo lies within ``near_m`` of the stem."""
    return df["sample_distance_m"].to_numpy(float) < near_m


def _split_species(df: pd.DataFrame, near_m: float) -> list[str]:
    """The species of one dataset's keys whose tree pulses near the stem and those further out
    each come from at least :data:`NEAR_STEM_MIN_SAMPLES` field samples."""
    tree, near = _tree(df), _near(df, near_m)
    count = [df[part].groupby("species")["sample_id"].nunique() for part in (tree & near, tree & ~near)]
    both = pd.concat(count, axis=1).fillna(0).min(axis=1)
    return [str(sp) for sp in both.index[both >= NEAR_STEM_MIN_SAMPLES]]


def real_features(features: pd.DataFrame, keys: pd.DataFrame, strata: StrataSettings) -> pd.DataFrame:
    """The real feature rows of ``keys``' pulses, with ``compare``'s rules applied."""

    f = features.copy()
    if "source" in f.columns:
        f = f[f["source"].astype(str) == "real"]
    f["dataset"] = f["dataset"].astype(str)
    key_cols = ["dataset", "pulse_id", "sample_id", "species", "is_tree", "stratum"]
    f = f.drop(columns=[c for c in key_cols[2:] if c in f.columns])
    real = keys[key_cols].merge(f, on=["dataset", "pulse_id"], how="inner", validate="one_to_one")
    if real.empty:
        raise WaveforestError("diagnose: no real feature row matches the selected comparison pulses")
    return apply_rules(real, strata)


def with_pulses_under_crowns(selected: pa.Table, agc: pa.Table, fields: pd.DataFrame, year: int, calibration,
                             strata: StrataSettings) -> pa.Table:
    """``selected`` with its ``below_crown_set`` re-drawn by the pulses' own first CFD echo.

    The real side of the stratum "below crown" is chosen by the detector that chooses its twins
    (:class:`.twins.StudySimulator`): every pulse of the dataset gets the CFD echoes of its own waveform
    (:func:`own_cfd_echoes`), and ``select``'s rules
    (:func:`waveforest.model.selection.select_pulses`) on those echoes say which lie under a
    compared crown. Those rows carry their CFD echoes and replace the pulses' ``select`` rows,
    also those of a crown the DR echo gave them (a DR that fired on a weak crown return the
    CFD passes over; its twin is sorted by the CFD too).

    Parameters
    ----------
    selected : pa.Table
        ``select`` table of one dataset.
    agc : pa.Table
        Its AGC-normalised pulse table (``agc`` stage).
    fields : DataFrame
        fields.csv.
    year : int
        The dataset's campaign year.
    calibration : waveforest.sensor.calibration.Calibration
    strata : StrataSettings
    """

    own = select_pulses(own_cfd_echoes(agc, calibration, strata.sensor), fields, year, strata.rules)
    under = own.filter(own.column("below_crown_set"))
    keep = pc.invert(pc.is_in(selected.column("pulse_id"), value_set=under.column("pulse_id")))
    if "below_crown_set" in selected.column_names:
        keep = pc.and_(keep, pc.invert(pc.fill_null(selected.column("below_crown_set"), False)))
    ordinary = selected.filter(keep)
    under = under.select([c for c in ordinary.column_names if c in under.column_names])
    return pa.concat_tables([ordinary, under], promote_options="permissive")


def with_ring_pulses(selected: pa.Table, agc: pa.Table, fields: pd.DataFrame, year: int,
                     strata: StrataSettings) -> pa.Table:
    """``selected`` with the pulses of the ring appended: every pulse of the dataset (its
    AGC-normalised table) that no sample takes and whose beam meets the ground between
    ``select.tree_radius_m`` and ``diagnose.ring_m`` of a compared tree's base
    (:func:`waveforest.model.selection.ring_pulses`), with its DR echoes (the real features'
    detector); ``ring_set`` marks them. Pulses already in ``selected`` are not added twice.
    :func:`apply_rules` keeps those whose first echo is low (the stratum :data:`RING`).
    """

    ring = ring_pulses(agc, fields, year, strata.rules, float(strata.ring_m))
    ring = ring.filter(pc.invert(pc.is_in(ring.column("pulse_id"), value_set=selected.column("pulse_id"))))
    ring = ring.select([c for c in dict.fromkeys((*selected.column_names, "ring_set")) if c in ring.column_names])
    return pa.concat_tables([selected, ring], promote_options="permissive")


def added_features(keys: pd.DataFrame, selected: dict, metas: dict, strata: StrataSettings) -> pd.DataFrame:
    """Real feature rows of the strata :data:`ADDED_STRATA` of ``keys``, from their rows in
    ``selected`` (under the crowns their own CFD echoes, :func:`with_pulses_under_crowns`; in
    the ring their DR echoes, :func:`with_ring_pulses`), with ``compare``'s rules.

    Parameters
    ----------
    keys : DataFrame
        :func:`pulse_keys`.
    selected : dict
        Dataset -> table of those functions.
    metas : dict
        Dataset -> calibration JSON dict.
    strata : StrataSettings
    """

    added = keys[keys["stratum"].isin(ADDED_STRATA)]
    parts = []
    for ds, rows in added.groupby("dataset", sort=True):
        table = selected[ds]
        sub = table.filter(pc.is_in(table.column("pulse_id"), value_set=pa.array(rows["pulse_id"].to_numpy(np.int64))))
        parts.append(feature_table(sub, {ds: metas[ds]}, replace(strata.sensor.features, decomposition=False)))
    return real_features(pd.concat(parts, ignore_index=True), added, strata) if parts else pd.DataFrame()
