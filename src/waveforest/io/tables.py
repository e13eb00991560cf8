"""The CSV tables of a campaign folder: ``datasets.csv``, ``fields.csv``, ``targets.csv``.

These are the files a user fills in for real data (the virtual campaign writes the same
schema), and this module is their one reader: every stage that reads a table calls
:func:`read_datasets`, :func:`read_fields` or :func:`read_targets`. Each checks the required
columns, their types and ranges, and returns a :class:`pandas.DataFrame`; a bad file ends in
one :class:`CampaignTableError` naming the file, the column (and row) and what was expected.

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

Every table holds at least one row; names (dataset, sample_id, target_id) are unique.
Every number is finite and within :data:`RANGES` (physical bounds, generous for any airborne
waveform campaign: e.g. an HDRF in (0, 1] -- a reference target brighter than a perfect
Lambertian reflector at nadir is a unit error --, a range in (0, 100 km), a divergence in
(0, 100] mrad, a scan zenith in [0, 90) degrees). ``species`` is a species slug of Table 1
(:func:`waveforest.species.species_slugs`), ``functional_group`` one of
:data:`waveforest.constants.FUNCTIONAL_GROUPS`, and a calibration target has an HDRF.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from waveforest.constants import FUNCTIONAL_GROUPS
from waveforest.errors import WaveforestError
from waveforest.io.csvfile import read_csv_file
from waveforest.species import species_slugs

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


@dataclass(frozen=True)
class Bounds:
    """The range a column's numbers must lie in (``closed``: the bound itself is allowed)."""

    lo: float = -np.inf
    hi: float = np.inf
    lo_closed: bool = False
    hi_closed: bool = False
    unit: str = ""

    def holds(self, v: np.ndarray) -> np.ndarray:
        """Finite and within the bounds."""
        with np.errstate(invalid="ignore"):
            lo = v >= self.lo if self.lo_closed else v > self.lo
            hi = v <= self.hi if self.hi_closed else v < self.hi
        return np.isfinite(v) & lo & hi

    def __str__(self) -> str:
        unit = f" {self.unit}" if self.unit else ""
        if np.isinf(self.lo) and np.isinf(self.hi):
            return f"a finite number ({self.unit})" if self.unit else "a finite number"
        return f"{'[' if self.lo_closed else '('}{self.lo:g}, {self.hi:g}{']' if self.hi_closed else ')'}{unit}"


_YEAR = Bounds(1900, 2200, True, True)
_COORD = Bounds(unit="m")
RANGES: dict[str, dict[str, Bounds]] = {
    "datasets": {
        "year": _YEAR,
        "mean_range_m": Bounds(0, 1e5, unit="m"),
        "pulse_width_fwhm_ns": Bounds(0, 1e3, unit="ns"),
        "footprint_diameter_m": Bounds(0, 1e3, unit="m"),
        "sampling_ns": Bounds(0, 1e3, unit="ns"),
        "divergence_mrad": Bounds(0, 100, hi_closed=True, unit="mrad"),
        "pulse_density_m2": Bounds(0, 1e6, unit="per m2"),
        "max_scan_zenith_deg": Bounds(0, 90, lo_closed=True, unit="degrees"),
    },
    "fields": {
        "year": _YEAR, "x": _COORD, "y": _COORD, "ground_z": _COORD,
        "height_m": Bounds(0, 150, True, True, "m"),
        "radius_m": Bounds(0, 1e3, unit="m"),
        "canopy_cover_pct": Bounds(0, 100, True, True, "%"),
    },
    "targets": {
        "year": _YEAR, "x": _COORD, "y": _COORD, "z": _COORD,
        "radius_m": Bounds(0, 1e3, unit="m"),
        "hdrf": Bounds(0, 1, hi_closed=True),
    },
}
"""Table -> column -> the :class:`Bounds` of its numbers (empty optional cells are allowed)."""


class CampaignTableError(WaveforestError):
    """A campaign CSV table that does not follow its schema."""


def _coerce(df: pd.DataFrame, name: str, kind: str, source: str, required: bool) -> None:
    col = df[name]
    if kind == "str":
        if required and col.isna().any():
            row = int(np.flatnonzero(col.isna().to_numpy())[0])
            raise CampaignTableError(f"{source}: column {name}, row {row + 2}: empty value; expected text")
        df[name] = col.astype("string").str.strip().astype(object).where(col.notna(), None)
        return
    values = pd.to_numeric(col, errors="coerce")
    bad = values.isna() & col.notna() & (col.astype(str).str.strip() != "")
    if bad.any():
        row = int(np.flatnonzero(bad.to_numpy())[0])
        raise CampaignTableError(
            f"{source}: column {name}, row {row + 2}: {col.iloc[row]!r} is not a number")
    empty = values.isna().to_numpy()
    if (kind != "float" or required) and empty.any():
        row = int(np.flatnonzero(empty)[0])
        raise CampaignTableError(f"{source}: column {name}, row {row + 2}: empty value; expected a number")
    if kind == "float":
        df[name] = values.astype(float)
        return
    v = values.to_numpy(dtype=np.float64)
    if kind == "int":
        wrong = ~(np.isfinite(v) & (v == np.round(v)))
        if wrong.any():
            row = int(np.flatnonzero(wrong)[0])
            raise CampaignTableError(f"{source}: column {name}, row {row + 2}: {col.iloc[row]!r}; expected an integer")
        df[name] = v.astype(np.int64)
    elif kind == "bool":
        wrong = ~np.isin(v, (0, 1))
        if wrong.any():
            row = int(np.flatnonzero(wrong)[0])
            raise CampaignTableError(f"{source}: column {name}, row {row + 2}: {col.iloc[row]!r}; expected 0 or 1")
        df[name] = v.astype(bool)


def _check_ranges(df: pd.DataFrame, ranges: dict, source: str) -> None:
    """Every given number of the columns of ``ranges`` is finite and within its bounds."""
    for name, bounds in ranges.items():
        if name not in df.columns:
            continue
        v = df[name].to_numpy(dtype=np.float64)
        wrong = ~np.isnan(v) & ~bounds.holds(v)  # NaN: an empty optional cell (required ones are refused)
        if wrong.any():
            row = int(np.flatnonzero(wrong)[0])
            raise CampaignTableError(f"{source}: column {name}, row {row + 2}: {v[row]:g}; expected {bounds}")


def _check_names(df: pd.DataFrame, name: str, known, what: str, source: str) -> None:
    wrong = ~df[name].isin(known).to_numpy()
    if wrong.any():
        row = int(np.flatnonzero(wrong)[0])
        raise CampaignTableError(f"{source}: column {name}, row {row + 2}: unknown {what} {df[name].iloc[row]!r}; "
                                 f"expected one of {', '.join(known)}")


def _read(path: str | Path, required: dict, optional: dict, key: str, table: str) -> pd.DataFrame:
    path = Path(path)
    df = read_csv_file(path, CampaignTableError, dtype=str, keep_default_na=True)
    missing = [c for c in required if c not in df.columns]
    if missing:
        raise CampaignTableError(
            f"{path}: missing column(s) {', '.join(missing)}; expected {', '.join(required)}")
    if df.empty:
        raise CampaignTableError(f"{path}: no rows; expected at least one row (one per {key})")
    for name, kind in required.items():
        _coerce(df, name, kind, str(path), required=True)
    for name, kind in optional.items():
        if name in df.columns:
            _coerce(df, name, kind, str(path), required=False)
        else:
            df[name] = np.nan if kind == "float" else None
    _check_ranges(df, RANGES[table], str(path))
    dup = df[key].duplicated()
    if dup.any():
        raise CampaignTableError(f"{path}: {key} {df[key][dup].iloc[0]!r} appears more than once; expected unique names")
    return df.reset_index(drop=True)


def read_datasets(path: str | Path) -> pd.DataFrame:
    """Read and check ``datasets.csv`` (one row per dataset; module docstring for the rules)."""
    return _read(path, _DATASET_COLUMNS, _DATASET_OPTIONAL, "dataset", "datasets")


def read_fields(path: str | Path) -> pd.DataFrame:
    """Read and check ``fields.csv`` (one row per field sample; module docstring for the rules)."""
    df = _read(path, _FIELD_COLUMNS, _FIELD_OPTIONAL, "sample_id", "fields")
    _check_names(df, "species", species_slugs(), "species", str(path))
    _check_names(df, "functional_group", FUNCTIONAL_GROUPS, "functional group", str(path))
    return df


def read_targets(path: str | Path) -> pd.DataFrame:
    """Read and check ``targets.csv`` (one row per reference target; module docstring for the rules)."""
    df = _read(path, _TARGET_COLUMNS, _TARGET_OPTIONAL, "target_id", "targets")
    no_hdrf = df["calibration"].to_numpy() & np.isnan(df["hdrf"].to_numpy(dtype=np.float64))
    if no_hdrf.any():
        row = int(np.flatnonzero(no_hdrf)[0])
        raise CampaignTableError(f"{path}: column hdrf, row {row + 2}: calibration target "
                                 f"{df['target_id'].iloc[row]!r} needs an HDRF in {RANGES['targets']['hdrf']}")
    return df


def dataset_year(datasets: pd.DataFrame, name: str, source: str | Path = "datasets.csv") -> int:
    """The year of dataset ``name``; a clear error if it is not listed."""
    return int(dataset_row(datasets, name, source)["year"])


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
    (docs/method.md §(a): footprint diameter (1/e) = R x divergence).
    """
    value = row.get("divergence_mrad", np.nan)
    if value is not None and np.isfinite(value) and value > 0:
        return float(value)
    return float(row["footprint_diameter_m"]) / float(row["mean_range_m"]) * 1e3
