"""The pipeline's own tables and documents under ``results/``: one reader and one writer each.

- select table, ``select/{dataset}.parquet``: :func:`read_select_table` (whole, checked) and
  :func:`read_select_columns` (some columns of several tables); written as a pulse table
  (:func:`.pulses.write_pulses`) with the columns of :data:`.pulses.SELECT_FIELDS`;
- feature table, ``features/{dataset}_{real,sim}.parquet``: :func:`read_feature_tables` /
  :func:`write_feature_table`;
- AGC fit, ``agc/{dataset}.json``: :func:`read_agc_fit` / :func:`write_agc_fit`; the fit's
  {dataset, a, b, n0} in the schema of ``agc/{dataset}.parquet``: :func:`read_agc_metadata` /
  :func:`agc_schema_metadata`;
- calibration, ``calibration/{dataset}.json``: :func:`read_calibration_json` /
  :func:`write_calibration_json`; its S(t), ``calibration/{dataset}.parquet``:
  :func:`read_system_waveform_table` / :func:`write_system_waveform_table`;
- classification, ``classify/{dataset}.json``: :func:`read_classify_result` /
  :func:`write_classify_result`;
- diagnosed model, ``diagnose/model.yaml``: :func:`read_model` / :func:`write_model`;
- a virtual campaign's ``truth.json`` (written by :mod:`waveforest.campaign.synthesize`):
  :func:`read_campaign_truth`.

Every reader raises one :class:`.errors.WaveforestError` naming the file for a missing,
unreadable or malformed input; every writer is atomic (:mod:`waveforest.atomic`).

``model.yaml`` layout (every number a plain float; ``.inf`` where an interval of
``nonlinearity`` reaches "off", i.e. no saturation)::

    verdict: named            # none | named | unexplained
    reason: ...               # one sentence: why the search stopped
    base_effects: {}          # simulate.effects the search started from
    effects:                  # named effects, in the order named (values after re-fitting)
      - name: understory
        value: 1.43           # fitted value (units of src/waveforest/effects.py)
        ci_low: 1.21          # cluster-bootstrap interval of the value
        ci_high: 1.73
        gap_reduction: 0.086  # test-half reduction of the total gap when it was named
        reduction_ci_low: 0.05
        reduction_ci_high: 0.12
        relative_reduction: 0.9   # share of the then excess gap removed
        round: 1
        look_alikes: []       # candidates of that round that explained the gap as well
        along_signature: ""   # empty when the gap named it; else its fit along the signature
    simulate_effects: {understory: 1.43}   # base + named: paste into simulate.effects
    gap: {before: ..., before_ci: [..], after: ..., after_ci: [..], noise_floor: ...}

``effects`` is an empty list unless the verdict is ``named``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import yaml

from waveforest.atomic import atomic_path, plain, write_json
from waveforest.effects import CATALOGUE
from waveforest.errors import WaveforestError
from waveforest.io.pulses import SELECT_FIELDS, TableError, read_pulses, write_table

# -- select tables ----------------------------------------------------------------------------

SELECT_FLAGS = ("single_echo_set", "classification_set", "comparison_set", "below_crown_set")
"""Boolean columns of a select table naming the sets a pulse belongs to."""


def read_select_table(path: str | Path) -> pa.Table:
    """A whole select table: a pulse table (:func:`.pulses.read_pulses`) with the select columns.

    Raises
    ------
    WaveforestError
        Missing or unreadable file, or a column of the pulse schema or of
        :data:`.pulses.SELECT_FIELDS` missing.
    """
    table = read_pulses(path)
    lacking = [f.name for f in SELECT_FIELDS if f.name not in table.column_names]
    if lacking:
        raise TableError(f"{path}: not a select table: no column(s) {', '.join(lacking)}")
    return table


def read_select_columns(paths, columns, required=("dataset", "pulse_id")) -> pd.DataFrame:
    """The ``columns`` that select tables (Parquet) have, concatenated into one DataFrame.

    A column of ``columns`` that a table lacks is left out (older tables); one of ``required``
    missing is an error. No paths: an empty frame with ``columns``.

    Raises
    ------
    WaveforestError
        An unreadable file, or a ``required`` column missing.
    """
    frames = []
    for p in paths:
        try:
            names = pq.read_schema(p).names
            frames.append(pq.read_table(p, columns=[c for c in columns if c in names]).to_pandas())
        except Exception as exc:  # pyarrow raises several types for non-Parquet input
            raise WaveforestError(f"{p}: not a readable Parquet table ({exc})") from None
        lacking = [c for c in required if c not in names]
        if lacking:
            raise WaveforestError(f"{p}: not a select table: no column(s) {', '.join(lacking)}")
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(columns=list(columns))


# -- feature tables ---------------------------------------------------------------------------

def write_feature_table(df: pd.DataFrame, path: str | Path) -> Path:
    """Write a feature table (one row per pulse: dataset, pulse_id, features) to Parquet, atomically."""
    return write_table(pa.Table.from_pandas(df, preserve_index=False), path)


def read_feature_tables(paths) -> pd.DataFrame:
    """Feature tables (Parquet, :func:`write_feature_table`) concatenated into one DataFrame.

    Raises
    ------
    WaveforestError
        No path given, or a file missing or unreadable.
    """
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


# -- JSON documents ---------------------------------------------------------------------------

def _read_mapping(path: Path, parse, error: type[Exception], fmt: str, missing: str, not_mapping: str) -> dict:
    """``parse`` of the text at ``path``, a dict; WaveforestError ``"{path}: {missing}"``, ``"{path}:
    not valid {fmt} (...)"`` (``error`` raised) or ``"{path}: {not_mapping}"``."""
    if not path.exists():
        raise WaveforestError(f"{path}: {missing}")
    try:
        d = parse(path.read_text())
    except error as exc:
        raise WaveforestError(f"{path}: not valid {fmt} ({exc})") from None
    if not isinstance(d, dict):
        raise WaveforestError(f"{path}: {not_mapping}")
    return d


def _read_json_document(path: str | Path, what: str) -> dict:
    """The JSON object at ``path``; WaveforestError if missing, invalid or not an object."""
    return _read_mapping(Path(path), json.loads, json.JSONDecodeError, "JSON", f"no such {what} file",
                         f"{what} is not a JSON object")


def read_campaign_truth(path: str | Path) -> dict:
    """``truth.json`` of a virtual campaign folder: at least ``seed`` (int) and ``effects``
    (name -> value, every effect of the catalogue); ``active_effects`` those switched on."""
    d = _read_json_document(path, "campaign truth")
    if not isinstance(d.get("seed"), int) or not isinstance(d.get("effects"), dict):
        raise WaveforestError(f"{path}: campaign truth without seed or effects")
    return d


# -- AGC --------------------------------------------------------------------------------------

AGC_METADATA_KEY = b"waveforest.agc"
"""Parquet schema-metadata key of a normalised pulse table: JSON with dataset, a, b, n0."""


def agc_schema_metadata(dataset: str, a: float, b: float, n0: float) -> dict:
    """Schema metadata of an AGC-normalised pulse table: {:data:`AGC_METADATA_KEY`: JSON bytes}."""
    return {AGC_METADATA_KEY: json.dumps({"dataset": dataset, "a": a, "b": b, "n0": n0}).encode()}


def read_agc_metadata(path: str | Path) -> dict:
    """The {dataset, a, b, n0} metadata of a normalised pulse table ({} if absent)."""
    try:
        md = pq.read_schema(path).metadata or {}
    except (pa.ArrowInvalid, OSError) as exc:
        raise WaveforestError(f"{path}: not a readable Parquet file ({exc})") from None
    if AGC_METADATA_KEY in md:
        return json.loads(md[AGC_METADATA_KEY])
    return {}


def write_agc_fit(fit: dict, path: str | Path) -> Path:
    """Write the AGC fit of Eq. 1 (``AGCFit.to_dict()``) as JSON, atomically."""
    return write_json(fit, path)


def read_agc_fit(path: str | Path) -> dict:
    """The AGC fit JSON (:func:`write_agc_fit`): a, b, n0, CV before / after, ..."""
    return _read_json_document(path, "AGC fit")


# -- calibration ------------------------------------------------------------------------------

CALIBRATION_KEYS = ("dataset", "noise_mean", "noise_sd")
"""Keys every calibration JSON has (not None)."""


def write_calibration_json(calibration: dict, path: str | Path) -> Path:
    """Write the calibration JSON of the ``calibrate`` stage, atomically."""
    return write_json(calibration, path)


def read_calibration_json(path: str | Path, required=CALIBRATION_KEYS) -> dict:
    """The calibration JSON written by the ``calibrate`` stage, checked for the ``required`` keys.

    Raises
    ------
    WaveforestError
        The file is missing, not valid JSON, or lacks one of ``required`` (or holds None there).
    """
    d = _read_json_document(path, "calibration")
    missing = [k for k in required if d.get(k) is None]
    if missing:
        raise WaveforestError(f"{path}: calibration lacks {', '.join(missing)}")
    return d


SYSTEM_WAVEFORM_KEY = b"waveforest.system_waveform"
"""Parquet schema-metadata key of an S(t) table: JSON of its metadata."""


def write_system_waveform_table(t_ns: np.ndarray, s: np.ndarray, s_sd: np.ndarray, meta: dict,
                                path: str | Path) -> Path:
    """Write S(t) as Parquet (columns t_ns, s, s_sd; ``meta`` as JSON in the schema), atomically."""
    path = Path(path)
    table = pa.table({"t_ns": t_ns, "s": s, "s_sd": s_sd})
    table = table.replace_schema_metadata({SYSTEM_WAVEFORM_KEY: json.dumps(meta, default=float).encode()})
    with atomic_path(path) as tmp:
        pq.write_table(table, tmp, compression="zstd")
    return path


def read_system_waveform_table(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, dict]:
    """S(t) written by :func:`write_system_waveform_table`.

    Returns
    -------
    t_ns, s : (n,) float64
    s_sd : (n,) float64, or None when absent or all NaN
    meta : dict

    Raises
    ------
    WaveforestError
        Missing or unreadable file, or no column t_ns or s.
    """
    path = Path(path)
    if not path.exists():
        raise WaveforestError(f"{path}: no such system-waveform file")
    try:
        table = pq.read_table(path)
    except (pa.ArrowInvalid, OSError) as exc:
        raise WaveforestError(f"{path}: not a readable Parquet file ({exc})") from None
    missing = [c for c in ("t_ns", "s") if c not in table.column_names]
    if missing:
        raise WaveforestError(f"{path}: system waveform lacks column(s) {', '.join(missing)}")
    t = table.column("t_ns").to_numpy().astype(np.float64)
    s = table.column("s").to_numpy().astype(np.float64)
    sd = None
    if "s_sd" in table.column_names:
        sd = table.column("s_sd").to_numpy(zero_copy_only=False).astype(np.float64)
        if np.isnan(sd).all():
            sd = None
    md = table.schema.metadata or {}
    meta = json.loads(md[SYSTEM_WAVEFORM_KEY]) if SYSTEM_WAVEFORM_KEY in md else {}
    return t, s, sd, meta


# -- classification ---------------------------------------------------------------------------

def write_classify_result(result: dict, path: str | Path) -> Path:
    """Write one dataset's classification (the ``classify`` stage's JSON), atomically."""
    return write_json(result, path)


def read_classify_result(path: str | Path) -> dict:
    """One ``classify/{dataset}.json``; ``dataset`` defaults to the file's stem.

    Raises
    ------
    WaveforestError
        Missing file, invalid JSON, or not a JSON object.
    """
    r = _read_json_document(path, "classification")
    r.setdefault("dataset", Path(path).stem)
    return r


# -- model.yaml -------------------------------------------------------------------------------

VERDICTS = ("none", "named", "unexplained", "inconclusive")
"""Outcomes of a diagnosis: no gap above its noise floor and the data not shown blind to any
candidate at its test value (``none``); effects named; a gap above the floor that no candidate
explains (``unexplained``); a gap not above the floor while the data cannot see some candidates at
their test values, or a gap above it with too few field samples to try a candidate
(``inconclusive``). ``model.yaml`` holds the search's; ``verdict.json`` the final one
(:func:`waveforest.diagnose.missing_effects.final_verdict`)."""

EFFECT_KEYS = ("name", "value", "ci_low", "ci_high", "gap_reduction")
"""Keys every entry of ``effects`` has; others are optional."""


def model_dict(verdict: str, named: list, *, reason: str = "", base_effects: dict | None = None,
               gap: dict | None = None, extra: dict | None = None) -> dict:
    """The content of ``model.yaml`` (plain values, infinities kept).

    Parameters
    ----------
    verdict : str
        ``none``, ``named`` or ``unexplained``.
    named : list
        Named effects: objects with the attributes of :data:`EFFECT_KEYS` (e.g.
        :class:`waveforest.diagnose.search.NamedEffect`) or dicts with those keys.
    reason : str
        Why the search stopped.
    base_effects : dict, optional
        Effects of the model the search started from (``simulate.effects``).
    gap : dict, optional
        Total gap before and after (numbers).
    extra : dict, optional
        Further top-level entries (settings, counts).
    """
    if verdict not in VERDICTS:
        raise WaveforestError(f"model.yaml: verdict {verdict!r}; expected one of {', '.join(VERDICTS)}")
    if (verdict == "named") != bool(named):
        raise WaveforestError(f"model.yaml: verdict {verdict!r} with {len(named)} named effect(s)")
    effects = []
    for e in named:
        d = dict(e) if isinstance(e, dict) else dict(vars(e))
        missing = [k for k in EFFECT_KEYS if k not in d]
        if missing:
            raise WaveforestError(f"model.yaml: effect entry lacks {', '.join(missing)}")
        if d["name"] not in CATALOGUE:
            raise WaveforestError(f"model.yaml: unknown effect {d['name']!r}")
        effects.append({k: d[k] for k in EFFECT_KEYS} | {k: v for k, v in d.items() if k not in EFFECT_KEYS})
    base = dict(base_effects or {})
    out = {
        "verdict": verdict,
        "reason": reason,
        "base_effects": base,
        "effects": effects,
        "simulate_effects": {**base, **{e["name"]: e["value"] for e in effects}},
    }
    if gap is not None:
        out["gap"] = gap
    if extra:
        out.update(extra)
    return plain(out, keep_inf=True)


def write_model(path: str | Path, model: dict) -> Path:
    """Write ``model`` (:func:`model_dict`) as YAML, atomically; returns the path."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(yaml.safe_dump(model, sort_keys=False, default_flow_style=False))
    return path


def read_model(path: str | Path) -> dict:
    """Read and check a ``model.yaml``.

    Returns
    -------
    dict
        With ``verdict`` in :data:`VERDICTS` and ``effects`` a list of dicts with
        :data:`EFFECT_KEYS`; ``effects_dict`` (name -> value) added for convenience.

    Raises
    ------
    WaveforestError
        Missing file, invalid YAML, or content against the layout above.
    """
    path = Path(path)
    m = _read_mapping(path, yaml.safe_load, yaml.YAMLError, "YAML", "no such file", "expected a mapping")
    if m.get("verdict") not in VERDICTS:
        raise WaveforestError(f"{path}: verdict {m.get('verdict')!r}; expected one of {', '.join(VERDICTS)}")
    effects = m.get("effects")
    if not isinstance(effects, list):
        raise WaveforestError(f"{path}: effects must be a list")
    for i, e in enumerate(effects):
        missing = [k for k in EFFECT_KEYS if not isinstance(e, dict) or k not in e]
        if missing:
            raise WaveforestError(f"{path}: effects[{i}] lacks {', '.join(missing)}")
        if e["name"] not in CATALOGUE:
            raise WaveforestError(f"{path}: effects[{i}]: unknown effect {e['name']!r}")
    m["effects_dict"] = {e["name"]: float(e["value"]) for e in effects}
    return m
