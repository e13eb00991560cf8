"""The CSV tables of a campaign folder: ``datasets.csv``, ``fields.csv``, ``targets.csv``.

These are the files a user fills in for real data (the virtual campaign writes the same
schema). Each reader checks the required columns and their types and returns a
:class:`pandas.DataFrame`; a bad file ends in one :class:`CampaignTableError` naming the file
and the column.

============  =====================================================================
table         required columns (types)
============  =====================================================================
datasets.csv  dataset (str), year (int), mean_range_m, pulse_width_fwhm_ns,
              footprint_diameter_m, sampling_ns (float); optional: las_file,
              trajectory_file, divergence_mrad, pulse_density_m2, max_scan_zenith_deg
fields.csv    sample_id (str), year (int), species (str slug), functional_group (str),
              x, y, ground_z, height_m, radius_m (float), is_tree (0/1); optional:
              stand_id, design, canopy_cover_pct (may be empty)
targets.csv   target_id (str), year (int), material (str), x, y, z, radius_m (float),
              calibration (0/1), agc (0/1); optional: hdrf (empty for AGC-only targets)
============  =====================================================================
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import WaveforestError

FUNCTIONAL_GROUPS = ("conifer", "broadleaf", "low_green", "low_barren_abiotic")
"""The four functional groups of METHOD.md (i4), in the paper's order."""

_DATASET_COLUMNS = {
    "dataset": "str", "year": "int",
    "mean_range_m": "float", "pulse_width_fwhm_ns": "float",
    "footprint_diameter_m": "float", "sampling_ns": "float",
}
_DATASET_OPTIONAL = {
    "las_file": "str", "trajectory_file": "str", "divergence_mrad": "float",
    "pulse_density_m2": "float", "max_scan_zenith_deg": "float",
}
_FIELD_COLUMNS = {
    "sample_id": "str", "year": "int", "species": "str", "functional_group": "str",
    "x": "float", "y": "float", "ground_z": "float", "height_m": "float",
    "radius_m": "float", "is_tree": "bool",
}
_FIELD_OPTIONAL = {"stand_id": "str", "design": "str", "canopy_cover_pct": "float"}
_TARGET_COLUMNS = {
    "target_id": "str", "year": "int", "material": "str",
    "x": "float", "y": "float", "z": "float", "radius_m": "float",
    "calibration": "bool", "agc": "bool",
}
_TARGET_OPTIONAL = {"hdrf": "float"}


class CampaignTableError(WaveforestError):
    """A campaign CSV table that does not follow its schema."""


def _coerce(df: pd.DataFrame, name: str, kind: str, source: str, required: bool) -> None:
    col = df[name]
    if kind == "str":
        if required and col.isna().any():
            raise CampaignTableError(f"{source}: column {name} has empty values")
        df[name] = col.astype("string").astype(object).where(col.notna(), None)
        return
    values = pd.to_numeric(col, errors="coerce")
    bad = values.isna() & col.notna() & (col.astype(str).str.strip() != "")
    if bad.any():
        row = int(np.flatnonzero(bad.to_numpy())[0])
        raise CampaignTableError(
            f"{source}: column {name}, row {row + 2}: {col.iloc[row]!r} is not a number")
    if kind == "float":
        df[name] = values.astype(float)
        if required and df[name].isna().any():
            raise CampaignTableError(f"{source}: column {name} has empty values")
        return
    if values.isna().any():
        raise CampaignTableError(f"{source}: column {name} has empty values")
    if kind == "int":
        if not np.all(values == np.round(values)):
            raise CampaignTableError(f"{source}: column {name}: expected integers")
        df[name] = values.astype(np.int64)
    elif kind == "bool":
        if not np.all(np.isin(values, (0, 1))):
            raise CampaignTableError(f"{source}: column {name}: expected 0 or 1")
        df[name] = values.astype(bool)


def _read(path: str | Path, required: dict, optional: dict, key: str) -> pd.DataFrame:
    path = Path(path)
    if not path.exists():
        raise CampaignTableError(f"{path}: no such file")
    try:
        df = pd.read_csv(path, dtype=str, keep_default_na=True)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise CampaignTableError(f"{path}: not a readable CSV table ({exc})") from None
    df.columns = [c.strip() for c in df.columns]
    missing = [c for c in required if c not in df.columns]
    if missing:
        raise CampaignTableError(
            f"{path}: missing column(s) {', '.join(missing)}; expected {', '.join(required)}")
    for name, kind in required.items():
        _coerce(df, name, kind, str(path), required=True)
    for name, kind in optional.items():
        if name in df.columns:
            _coerce(df, name, kind, str(path), required=False)
        else:
            df[name] = np.nan if kind == "float" else None
    dup = df[key].duplicated()
    if dup.any():
        raise CampaignTableError(f"{path}: {key} {df[key][dup].iloc[0]!r} appears more than once")
    return df.reset_index(drop=True)


def read_datasets(path: str | Path) -> pd.DataFrame:
    """Read and check ``datasets.csv`` (one row per dataset)."""
    df = _read(path, _DATASET_COLUMNS, _DATASET_OPTIONAL, "dataset")
    for name in ("mean_range_m", "sampling_ns", "footprint_diameter_m"):
        if np.any(df[name] <= 0):
            raise CampaignTableError(f"{path}: column {name}: expected values > 0")
    return df


def read_fields(path: str | Path) -> pd.DataFrame:
    """Read and check ``fields.csv`` (one row per field sample)."""
    df = _read(path, _FIELD_COLUMNS, _FIELD_OPTIONAL, "sample_id")
    if np.any(df["radius_m"] <= 0):
        raise CampaignTableError(f"{path}: column radius_m: expected values > 0")
    if np.any(df["height_m"] < 0):
        raise CampaignTableError(f"{path}: column height_m: expected values >= 0")
    return df


def read_targets(path: str | Path) -> pd.DataFrame:
    """Read and check ``targets.csv`` (one row per reference target)."""
    df = _read(path, _TARGET_COLUMNS, _TARGET_OPTIONAL, "target_id")
    if np.any(df["radius_m"] <= 0):
        raise CampaignTableError(f"{path}: column radius_m: expected values > 0")
    return df


def dataset_row(datasets: pd.DataFrame, name: str, source: str | Path = "datasets.csv") -> pd.Series:
    """The row of dataset ``name``; a clear error if it is not listed."""
    rows = datasets[datasets["dataset"] == name]
    if rows.empty:
        listed = ", ".join(datasets["dataset"].astype(str))
        raise CampaignTableError(f"{source}: dataset {name!r} is not listed (listed: {listed})")
    return rows.iloc[0]


def divergence_mrad(row: pd.Series) -> float:
    """Full-angle 1/e beam divergence of a dataset, mrad.

    ``divergence_mrad`` when given, else ``footprint_diameter_m / mean_range_m``
    (METHOD.md a: footprint diameter (1/e) = R x divergence).
    """
    value = row.get("divergence_mrad", np.nan)
    if value is not None and np.isfinite(value) and value > 0:
        return float(value)
    return float(row["footprint_diameter_m"]) / float(row["mean_range_m"]) * 1e3
