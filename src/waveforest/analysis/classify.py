"""Real-data classification of four functional groups (docs/method.md §(i4), the Table 4 analogue).

Per dataset:

1. the classification set: selected real pulses with a single DR echo (``single_echo_set`` of
   ``select``) of the species that have at least ``select.min_pulses`` such pulses in at least
   one processed dataset (Table 1's rule; :func:`species_table` counts them over every
   dataset's selection). Given one feature table only, the counts are those of that table
   (``select``'s own ``classification_set`` when the table has it);
2. features (default E and Apeak) divided by their mean over the dataset's single-echo
   sand-road pulses (sand road = 1; it is the normaliser only and takes no part in the LDA);
   heights (H, maxH) are not divided;
3. LDA (class-frequency priors) of the four functional groups of ``fields.csv``, at two
   levels: single pulses ("1-pulse") and the mean features of each field sample
   ("mean-of-sample");
4. overall accuracy, Cohen's kappa and the confusion matrix, by resubstitution (the paper's
   scheme) and by cross-validation whose folds never split a field sample.

A pulse without a value of a feature set (no first-echo segment) takes no part in that set's
LDA; each set records how many left (``n_dropped``) and why. The result's ``n_pulses``,
``n_samples`` and per-group counts are those of the main set's LDA.

Extras: other feature sets (default E + Apeak + FWHM, the paper: < 1 pp gain; E + Apeak +
maxH, the paper's "+ max H per sample": the largest first-echo height H among the sample's
classification-set pulses, given to each of its pulses at the 1-pulse level), and the
three-species LDA on real data (birch / raspberry / fireweed, features Apeak, FWHM, E,
1-pulse and 5-pulse means of consecutive pulses of one sample).

A level that cannot be computed is null, with a ``reason`` string beside it.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import pandas as pd

from waveforest import __version__
from waveforest.errors import WaveforestError, WaveforestWarning
from waveforest.sensor.features import DECOMPOSITION_FEATURES
from waveforest.stats import lda

THREE_SPECIES_FEATURES = ("Apeak", "FWHM", "E")
"""Features of the three-species LDA (as in the sensor study, docs/method.md §(i3))."""

SAMPLE_FEATURES = {"maxH": "H"}
"""Sample-level features: name -> the pulse column whose maximum over the sample it is."""

HEIGHT_FEATURES = ("H", "maxH", "gd_depth", "gd_last_H", "gd_n")
"""Heights and distances (m) and the echo count: not divided by the normaliser (the sand road's
H and depth are about 0, its count about 1)."""

NORMALISED_BY = {"gd_later_A": "Apeak"}
"""Intensities the normaliser has none of (its pulses hold one echo: no later echoes), divided by
its mean of another intensity on the same radiometric scale (DN) instead of their own."""


@dataclass(frozen=True)
class ClassifySettings:
    """The classification (config section ``classify``, with ``select.min_pulses`` and the seed).

    features : features of the main LDA.  extra_feature_sets : further feature sets.
    normaliser : species slug whose mean features become 1.  groups : functional groups
    classified.  three_species : species of the three-species LDA.  group_size : pulses per
    mean of its multi-pulse level.  cv_folds : folds of the sample-grouped cross-validation.
    min_pulses : Table 1's single-echo pulses per species.  seed : study seed (the folds).
    """

    features: tuple
    extra_feature_sets: tuple
    normaliser: str
    groups: tuple
    three_species: tuple
    group_size: int
    cv_folds: int
    min_pulses: int
    seed: int


def _real(df: pd.DataFrame) -> pd.DataFrame:
    return df[df["source"].astype(str) == "real"] if "source" in df.columns else df


def single_echo(df: pd.DataFrame) -> np.ndarray:
    """(n,) bool, the per-pulse part of the classification rule: ``select``'s
    ``single_echo_set``; for tables without it, one DR echo and not in ``below_crown_set``."""
    if "single_echo_set" in df.columns:
        return df["single_echo_set"].eq(True).to_numpy()
    out = df["n_echoes"].to_numpy() == 1
    if "below_crown_set" in df.columns:
        out &= ~df["below_crown_set"].eq(True).to_numpy()
    return out


def species_table(selected: pd.DataFrame, min_pulses: int) -> pd.DataFrame:
    """The Table 1 analogue: single-echo real pulses per species and dataset.

    Parameters
    ----------
    selected : DataFrame
        Selected pulses of one or more datasets (species; dataset, functional_group ("?" when
        absent); source; ``single_echo_set`` or n_echoes).
    min_pulses : int

    Returns
    -------
    DataFrame
        One row per (species, functional_group) of ``selected`` (sorted), columns species,
        functional_group, one int column per dataset (sorted names; 0 where none), max_pulses
        and included (max_pulses >= ``min_pulses``: the species is in every dataset's
        classification set).
    """
    real = _real(selected)
    keys = ["species", "functional_group"]
    d = pd.DataFrame({k: real[k].astype(str).to_numpy(object) if k in real.columns else "?"
                      for k in ["dataset"] + keys})
    d["single"] = single_echo(real)
    datasets = sorted(d["dataset"].unique())
    counts = d[d["single"]].groupby(keys + ["dataset"]).size().unstack("dataset")
    pairs = pd.MultiIndex.from_frame(d[keys].drop_duplicates().sort_values(keys))
    counts = counts.reindex(index=pairs, columns=datasets).fillna(0).astype(np.int64)
    table = counts.reset_index()
    table.columns = keys + datasets
    table["max_pulses"] = counts.max(axis=1).to_numpy() if datasets else 0
    table["included"] = table["max_pulses"] >= int(min_pulses)
    return table


def classification_rows(features: pd.DataFrame, min_pulses: int, included=None) -> pd.DataFrame:
    """The classification set of one dataset's feature table (see module docstring, step 1).

    ``included``: the species that pass the rule over every dataset (:func:`species_table`).
    Without it the rule counts the table's own pulses, or takes ``select``'s
    ``classification_set`` flag (the same rule, counted within the dataset) when present.
    """
    df = _real(features)
    if included is None:
        if "classification_set" in df.columns:
            return df[df["classification_set"].eq(True).to_numpy()].copy()
        table = species_table(df, min_pulses)
        included = table.loc[table["included"], "species"]
    keep = single_echo(df) & df["species"].astype(str).isin(list(included)).to_numpy()
    return df[keep].copy()


def add_sample_features(df: pd.DataFrame) -> pd.DataFrame:
    """Add the :data:`SAMPLE_FEATURES` columns: the maximum of their pulse column over each
    sample's rows of ``df``, given to every row of the sample (NaN pulse values ignored)."""
    df = df.copy()
    for name, column in SAMPLE_FEATURES.items():
        df[name] = df.groupby("sample_id", sort=False)[column].transform("max").to_numpy(float)
    return df


def normalise(df: pd.DataFrame, features, normaliser: str, reference: pd.DataFrame | None = None
              ) -> tuple[pd.DataFrame, dict]:
    """Divide ``features`` by their mean over the ``normaliser`` species' pulses (those of
    :data:`NORMALISED_BY` by its mean of the feature named there).

    ``reference`` (default ``df``) holds the pulses the mean is taken over. Returns the
    normalised copy and a record of the divisors. Without normaliser pulses the features are
    left as they are (record ``{"species": None, "n": 0, "reason": ...}``) and a warning is
    issued.
    """
    df = df.copy()
    reference = df if reference is None else reference
    ref = reference[reference["species"].astype(str) == normaliser]
    if ref.empty:
        reason = f"no single-echo {normaliser} pulses in the dataset: features are not normalised"
        warnings.warn(reason, WaveforestWarning, stacklevel=2)
        return df, {"species": None, "n": 0, "reason": reason}
    record = {"species": normaliser, "n": int(len(ref))}
    for f in features:
        by = NORMALISED_BY.get(f, f)
        mean = float(np.nanmean(ref[by].to_numpy(float)))
        if not np.isfinite(mean) or mean == 0:
            raise WaveforestError(f"normaliser {normaliser}: mean {by} is {mean}; cannot normalise {f}")
        df[f] = df[f].to_numpy(float) / mean
        record[f] = mean
    return df, record


def _too_few(what: str, counts: dict, dropped: int, features) -> str:
    """Why an LDA of ``what`` (groups, species) with ``counts`` items per class cannot run."""
    have = [k for k, n in counts.items() if n]
    none = [k for k, n in counts.items() if not n]
    text = f"LDA needs at least 2 {what} with pulses; "
    text += f"only {have[0]} has any" if have else "none has any"
    if none:
        text += f" (0 pulses: {', '.join(none)})"
    if dropped:
        text += f"; {dropped} pulse(s) lack a finite {' or '.join(features)}"
    return text


def dropped_reason(df: pd.DataFrame, features) -> str | None:
    """Why pulses of ``df`` leave an LDA on ``features`` (they lack a value of one); None if none do."""
    lacking = df[list(features)].isna()
    bad = lacking.any(axis=1).to_numpy()
    if not bad.any():
        return None
    names = [f for f in features if lacking[f].any()]
    text = f"no value of {' or '.join(names)}"
    if "Npeaks" in df.columns and (df.loc[bad, "Npeaks"].to_numpy() == 0).all():
        text += ": no first-echo segment above the noise threshold, Npeaks 0"
    return text


def _levels(df: pd.DataFrame, features, labels, folds: int, seed: int) -> dict:
    """LDA at both levels on the pulses of ``df`` with every one of ``features``: ``n_pulses`` of
    them; ``n_dropped`` without, ``dropped_reason`` why (:func:`dropped_reason`)."""
    d = df.dropna(subset=list(features))
    x = d[list(features)].to_numpy(float)
    y = d["functional_group"].astype(str).to_numpy(object)
    groups = d["sample_id"].astype(str).to_numpy(object)
    counts = {g: int(np.count_nonzero(y == g)) for g in labels}
    present = [g for g in labels if counts[g]]
    out = {"features": list(features), "groups_present": present,
           "groups_missing": [g for g in labels if not counts[g]],
           "n_pulses": int(len(d)), "n_samples": int(d["sample_id"].nunique()),
           "n_dropped": int(len(df) - len(d)), "dropped_reason": dropped_reason(df, features), "reason": None}
    if len(present) < 2:
        out["one_pulse"] = out["mean_of_sample"] = None
        out["reason"] = _too_few("functional groups", counts, len(df) - len(d), features)
        return out
    out["one_pulse"] = lda.evaluate(x, y, groups, present, folds, seed)
    means = d.groupby("sample_id", sort=True).agg(
        **{f: (f, "mean") for f in features}, functional_group=("functional_group", "first"))
    xm = means[list(features)].to_numpy(float)
    ym = means["functional_group"].astype(str).to_numpy(object)
    out["mean_of_sample"] = lda.evaluate(xm, ym, means.index.to_numpy(object), present, folds, seed)
    return out


def _with_gain(block: dict, main: dict) -> dict:
    """Add ``gain_pp``: the block's accuracy minus the main set's, percentage points, per level
    and scheme (None where either is missing; the paper quotes its extras as such gains)."""
    gain = {}
    for level in ("one_pulse", "mean_of_sample"):
        gain[level] = {}
        for scheme in ("resubstitution", "cross_validated"):
            a = (block.get(level) or {}).get(scheme)
            b = (main.get(level) or {}).get(scheme)
            gain[level][scheme] = 100.0 * (a["accuracy"] - b["accuracy"]) if a and b else None
    return dict(block, gain_pp=gain)


def _three_species(df: pd.DataFrame, species, group_size: int, folds: int, seed: int) -> dict:
    features = list(THREE_SPECIES_FEATURES)
    sub = df[df["species"].isin(list(species))]
    d = sub.dropna(subset=features)
    counts = {s: int((d["species"] == s).sum()) for s in species}
    present = [s for s in species if counts[s]]
    out = {"species": present, "requested": list(species), "features": features,
           "group_size": int(group_size), "n_pulses": int(len(d)), "pulses_per_species": counts,
           "reason": None, "multi_pulse_reason": None}
    if len(present) < 2:
        out["one_pulse"] = out["multi_pulse"] = None
        out["reason"] = out["multi_pulse_reason"] = _too_few("species", counts, len(sub) - len(d), features)
        return out
    x = d[features].to_numpy(float)
    y = d["species"].astype(str).to_numpy(object)
    groups = d["sample_id"].astype(str).to_numpy(object)
    out["one_pulse"] = lda.evaluate(x, y, groups, present, folds, seed)
    order = d["pulse_id"].to_numpy() if "pulse_id" in d.columns else np.arange(len(d))
    xm, ym, units = lda.consecutive_means(x, y, order, groups, group_size)
    if len(set(ym)) >= 2:
        out["multi_pulse"] = lda.evaluate(xm, ym, units, [s for s in present if s in set(ym)], folds, seed)
    else:
        out["multi_pulse"] = None
        have = sorted(set(ym))
        out["multi_pulse_reason"] = (
            f"a {group_size}-pulse mean needs {group_size} pulses of one sample; "
            + (f"only {have[0]} has such samples" if have else "no species has such samples"))
    return out


def classify_dataset(features: pd.DataFrame, settings: ClassifySettings, selection: pd.DataFrame | None = None
                     ) -> dict:
    """Classify one dataset's real pulses; return the JSON-ready result.

    Parameters
    ----------
    features : DataFrame
        Feature table of one dataset (``waveforest features`` of the selected real pulses:
        dataset, pulse_id, sample_id, species, functional_group, n_echoes, Apeak, E, FWHM, H,
        ..., and ``select``'s flags when present).
    settings : ClassifySettings
    selection : DataFrame, optional
        Selected pulses of every processed dataset (dataset, species, functional_group,
        ``single_echo_set`` or n_echoes): the species rule counts over them. None: over
        ``features`` alone.
    """
    min_pulses = settings.min_pulses
    feats = list(settings.features)
    extra = [list(s) for s in settings.extra_feature_sets]
    # a decomposition set on a feature table made without the decomposition is left out
    extra = [s for s in extra if all(f in features.columns for f in s if f in DECOMPOSITION_FEATURES)]
    every = sorted(set(feats) | {f for s in extra for f in s} | set(THREE_SPECIES_FEATURES))
    needed = sorted({SAMPLE_FEATURES.get(f, f) for f in every})
    missing = [f for f in needed + ["species", "functional_group", "sample_id", "n_echoes"]
               if f not in features.columns]
    if missing:
        raise WaveforestError(f"feature table lacks column(s) {', '.join(missing)}")
    names = features["dataset"].unique().tolist() if "dataset" in features.columns else ["?"]
    if selection is None:
        table = species_table(features, min_pulses)
        rows = classification_rows(features, min_pulses)
        scope = "the dataset's own pulses (no other dataset's selection given)"
    else:
        table = species_table(selection, min_pulses)
        rows = classification_rows(features, min_pulses, table.loc[table["included"], "species"])
        scope = "every processed dataset (Table 1: in at least one dataset)"
    rows = add_sample_features(rows)
    # the normaliser: every single-echo real pulse of the sand road (it need not pass min_pulses)
    real = _real(features)
    rows, record = normalise(rows, [f for f in every if f not in HEIGHT_FEATURES], settings.normaliser,
                             real[single_echo(real)])
    labels = [g for g in settings.groups]
    lda_rows = rows[(rows["species"].astype(str) != settings.normaliser)
                    & rows["functional_group"].astype(str).isin(labels)]
    seed = settings.seed
    folds = settings.cv_folds
    main = _levels(lda_rows, feats, labels, folds, seed)
    used = lda_rows.dropna(subset=feats)  # the main LDA's pulses: every count below is theirs
    datasets = [k for k in table.columns if k not in ("species", "functional_group", "max_pulses", "included")]
    result = {
        "dataset": str(names[0]) if len(names) == 1 else [str(n) for n in names],
        "waveforest": __version__,
        "scheme": "LDA, class-frequency priors; resubstitution (paper) and cross-validation "
                  "with folds that never split a field sample",
        "groups": labels,
        "normaliser": record,
        "n_pulses": int(len(used)),
        "n_samples": int(used["sample_id"].nunique()),
        "pulses_per_sample": float(len(used) / max(used["sample_id"].nunique(), 1)),
        "pulses_per_group": {g: int((used["functional_group"] == g).sum()) for g in labels},
        "samples_per_group": {g: int(used.loc[used["functional_group"] == g, "sample_id"].nunique())
                              for g in labels},
        "species": {str(k): int(v) for k, v in used["species"].value_counts().sort_index().items()},
        "species_rule": {"min_pulses": min_pulses, "counted_over": scope, "datasets": datasets},
        "species_table": [
            {"species": r["species"], "functional_group": r["functional_group"],
             "pulses": {d: int(r[d]) for d in datasets}, "max_pulses": int(r["max_pulses"]),
             "included": bool(r["included"])}
            for r in table.to_dict("records")],
        "main": main,
        "extra": [_with_gain(_levels(lda_rows, s, labels, folds, seed), main) for s in extra],
        "three_species": _three_species(rows, list(settings.three_species), settings.group_size, folds, seed),
    }
    return result
