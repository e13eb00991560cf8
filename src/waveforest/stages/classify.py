"""Real-data classification of four functional groups (docs/method.md §(i4), the Table 4 analogue).

Per dataset:

1. the classification set: selected real pulses with a single DR echo, of species with at
   least ``select.min_pulses`` such pulses (the flag ``classification_set`` of ``select``; the
   rule is re-applied from ``n_echoes`` when a feature table lacks the flag);
2. features (default E and Apeak) divided by their mean over the dataset's single-echo
   sand-road pulses (sand road = 1; it is the normaliser only and takes no part in the LDA);
3. LDA (class-frequency priors) of the four functional groups of ``fields.csv``, at two
   levels: single pulses ("1-pulse") and the mean features of each field sample
   ("mean-of-sample");
4. overall accuracy, Cohen's kappa and the confusion matrix, by resubstitution (the paper's
   scheme) and by cross-validation whose folds never split a field sample.

Extras: other feature sets (default E + Apeak + FWHM; the paper: < 1 pp gain), and the
three-species LDA on real data (birch / raspberry / fireweed, features Apeak, FWHM, E,
1-pulse and 5-pulse means of consecutive pulses of one sample).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import click
import numpy as np
import pandas as pd
import pyarrow.parquet as pq

from waveforest import __version__
from waveforest.atomic import write_json
from waveforest.cliutil import (
    EXISTING_FILE,
    OUT_FILE,
    MultiValueCommand,
    MultiValueOption,
    stage_options,
)
from waveforest.errors import WaveforestError, WaveforestWarning
from waveforest.stats import lda

THREE_SPECIES_FEATURES = ("Apeak", "FWHM", "E")
"""Features of the three-species LDA (as in the sensor study, docs/method.md §(i3))."""


def classification_rows(features: pd.DataFrame, min_pulses: int) -> pd.DataFrame:
    """The classification set of a feature table (see module docstring, step 1)."""
    df = features
    if "source" in df.columns:
        df = df[df["source"].astype(str) == "real"]
    if "classification_set" in df.columns:
        return df[df["classification_set"].astype(bool)].copy()
    single = df[df["n_echoes"].to_numpy() == 1]
    counts = single["species"].value_counts()
    return single[single["species"].isin(counts.index[counts >= min_pulses])].copy()


def normalise(df: pd.DataFrame, features, normaliser: str, reference: pd.DataFrame | None = None
              ) -> tuple[pd.DataFrame, dict]:
    """Divide ``features`` by their mean over the ``normaliser`` species' pulses.

    ``reference`` (default ``df``) holds the pulses the mean is taken over. Returns the
    normalised copy and a record of the divisors. Without normaliser pulses the features are
    left as they are (record ``{"species": None}``) and a warning is issued.
    """
    df = df.copy()
    reference = df if reference is None else reference
    ref = reference[reference["species"].astype(str) == normaliser]
    if ref.empty:
        warnings.warn(f"no {normaliser} pulses: features are not normalised", WaveforestWarning, stacklevel=2)
        return df, {"species": None, "n": 0}
    record = {"species": normaliser, "n": int(len(ref))}
    for f in features:
        mean = float(np.nanmean(ref[f].to_numpy(float)))
        if not np.isfinite(mean) or mean == 0:
            raise WaveforestError(f"normaliser {normaliser}: mean {f} is {mean}; cannot normalise")
        df[f] = df[f].to_numpy(float) / mean
        record[f] = mean
    return df, record


def _levels(df: pd.DataFrame, features, labels, folds: int, seed: int) -> dict:
    d = df.dropna(subset=list(features))
    x = d[list(features)].to_numpy(float)
    y = d["functional_group"].astype(str).to_numpy(object)
    groups = d["sample_id"].astype(str).to_numpy(object)
    present = [g for g in labels if g in set(y)]
    out = {"features": list(features)}
    if len(present) < 2:
        out["one_pulse"] = out["mean_of_sample"] = None
        return out
    out["one_pulse"] = lda.evaluate(x, y, groups, present, folds, seed)
    means = d.groupby("sample_id", sort=True).agg(
        **{f: (f, "mean") for f in features}, functional_group=("functional_group", "first"))
    xm = means[list(features)].to_numpy(float)
    ym = means["functional_group"].astype(str).to_numpy(object)
    out["mean_of_sample"] = lda.evaluate(xm, ym, means.index.to_numpy(object), present, folds, seed)
    out["n_pulses"] = int(len(d))
    out["n_samples"] = int(len(means))
    return out


def _three_species(df: pd.DataFrame, species, group_size: int, folds: int, seed: int) -> dict | None:
    d = df[df["species"].isin(list(species))].dropna(subset=list(THREE_SPECIES_FEATURES))
    present = [s for s in species if s in set(d["species"])]
    if len(present) < 2:
        return None
    x = d[list(THREE_SPECIES_FEATURES)].to_numpy(float)
    y = d["species"].astype(str).to_numpy(object)
    groups = d["sample_id"].astype(str).to_numpy(object)
    out = {"species": present, "features": list(THREE_SPECIES_FEATURES),
           "one_pulse": lda.evaluate(x, y, groups, present, folds, seed)}
    order = d["pulse_id"].to_numpy() if "pulse_id" in d.columns else np.arange(len(d))
    xm, ym, units = lda.consecutive_means(x, y, order, groups, group_size)
    out["group_size"] = int(group_size)
    out["n_pulses"] = int(len(d))
    if len(set(ym)) >= 2:
        out["multi_pulse"] = lda.evaluate(xm, ym, units, [s for s in present if s in set(ym)], folds, seed)
    else:
        out["multi_pulse"] = None
    return out


def classify_dataset(features: pd.DataFrame, cfg: dict) -> dict:
    """Classify one dataset's real pulses; return the JSON-ready result.

    Parameters
    ----------
    features : DataFrame
        Feature table of one dataset (``waveforest features`` of the selected real pulses:
        dataset, pulse_id, sample_id, species, functional_group, n_echoes, Apeak, E, FWHM, ...,
        and ``classification_set`` when present).
    cfg : dict
        Loaded study config (sections ``classify``, ``select``, ``seed``).
    """
    c = cfg["classify"]
    feats = list(c["features"])
    extra = [list(s) for s in c["extra_feature_sets"]]
    every = sorted(set(feats) | {f for s in extra for f in s} | set(THREE_SPECIES_FEATURES))
    missing = [f for f in every + ["species", "functional_group", "sample_id", "n_echoes"]
               if f not in features.columns]
    if missing:
        raise WaveforestError(f"feature table lacks column(s) {', '.join(missing)}")
    names = features["dataset"].unique().tolist() if "dataset" in features.columns else ["?"]
    rows = classification_rows(features, int(cfg["select"]["min_pulses"]))
    # the normaliser: every single-echo real pulse of the sand road (it need not pass min_pulses)
    real = features[features["source"].astype(str) == "real"] if "source" in features.columns else features
    rows, record = normalise(rows, every, c["normaliser"], real[real["n_echoes"].to_numpy() == 1])
    labels = [g for g in c["groups"]]
    lda_rows = rows[(rows["species"].astype(str) != c["normaliser"])
                    & rows["functional_group"].astype(str).isin(labels)]
    seed = int(cfg["seed"])
    folds = int(c["cv_folds"])
    main = _levels(lda_rows, feats, labels, folds, seed)
    result = {
        "dataset": str(names[0]) if len(names) == 1 else [str(n) for n in names],
        "waveforest": __version__,
        "scheme": "LDA, class-frequency priors; resubstitution (paper) and cross-validation "
                  "with folds that never split a field sample",
        "groups": labels,
        "normaliser": record,
        "n_pulses": int(len(lda_rows)),
        "n_samples": int(lda_rows["sample_id"].nunique()),
        "pulses_per_sample": float(len(lda_rows) / max(lda_rows["sample_id"].nunique(), 1)),
        "pulses_per_group": {g: int((lda_rows["functional_group"] == g).sum()) for g in labels},
        "species": {str(k): int(v) for k, v in lda_rows["species"].value_counts().sort_index().items()},
        "main": main,
        "extra": [_levels(lda_rows, s, labels, folds, seed) for s in extra],
        "three_species": _three_species(rows, list(c["three_species"]), int(c["group_size"]), folds, seed),
    }
    return result


def read_feature_tables(paths) -> pd.DataFrame:
    """Concatenate feature tables (Parquet) into one DataFrame."""

    frames = []
    for p in paths:
        p = Path(p)
        if not p.exists():
            raise WaveforestError(f"{p}: no such file")
        try:
            frames.append(pq.read_table(p).to_pandas())
        except Exception as exc:  # pyarrow raises several types for non-Parquet input
            raise WaveforestError(f"{p}: not a readable Parquet table ({exc})") from None
    if not frames:
        raise WaveforestError("no feature table given")
    return pd.concat(frames, ignore_index=True)


def attach_selection(features: pd.DataFrame, selected: pd.DataFrame) -> pd.DataFrame:
    """Add the columns of ``select`` that a feature table lacks, joined on (dataset, pulse_id)."""
    keys = ["dataset", "pulse_id"]
    cols = [c for c in selected.columns if c not in features.columns or c in keys]
    if len(cols) == len(keys):
        return features
    return features.merge(selected[cols], on=keys, how="left", validate="many_to_one")


def run(features_path, out_path, cfg: dict, select_paths=()) -> dict:
    """The ``classify`` stage: one dataset's feature table -> JSON (Table 4 row and more).

    ``select_paths`` (optional): the dataset's ``select`` tables, joined to add flags
    (``classification_set``) that the feature table lacks.
    """
    features = read_feature_tables([features_path])
    if select_paths:

        cols = ["dataset", "pulse_id", "classification_set", "comparison_set", "height_m"]
        sel = pd.concat([pq.read_table(p, columns=cols).to_pandas() for p in select_paths],
                        ignore_index=True)
        features = attach_selection(features, sel)
    result = classify_dataset(features, cfg)
    write_json(result, out_path)
    return result




@click.command("classify", cls=MultiValueCommand)
@click.argument("features", type=EXISTING_FILE)
@click.option("--select", "select_paths", cls=MultiValueOption, type=EXISTING_FILE,
              help="The dataset's select table, to add flags a feature table lacks (optional).")
@click.option("--out", type=OUT_FILE, required=True, help="Output JSON.")
@stage_options
def classify(features, select_paths, out, cfg):
    """LDA of four functional groups on one dataset's real pulses (docs/method.md §(i4), Table 4).

    FEATURES is the feature table of the dataset's selected real pulses.
    """

    r = run(features, out, cfg, select_paths=select_paths)
    one = r["main"].get("one_pulse") or {}
    acc = (one.get("resubstitution") or {}).get("accuracy", float("nan"))
    click.echo(f"classify: {r['dataset']}: {r['n_pulses']} pulses, {r['n_samples']} samples, "
               f"1-pulse accuracy {100 * acc:.1f} % -> {out}")
