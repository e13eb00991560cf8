"""Reference targets of a campaign and the pulses that hit them (METHOD.md b, e).

``targets.csv`` (the schema the virtual campaign writes and a user fills in):
target_id, year, material, hdrf (nadir HDRF at 1064 nm; empty for AGC-only targets),
calibration (0/1: used for S(t), Eq. 8), agc (0/1: used to fit b of Eq. 1), x, y, z, radius_m.

``datasets.csv``: dataset, year, ... (only these two columns are needed here; sampling_ns
and the others are read when present).

A pulse belongs to a target if its first DR echo (echo_x[0], echo_y[0]) lies within
radius_m of the target centre (x, y) and the target's year is the dataset's year; if several
targets qualify, the nearest centre wins.

The readers here are deliberately small: the sensor stages need only these columns, and the
analysis package (below this one in the module order) keeps the full campaign-table checks.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa

from ..errors import WaveforestError
from ..io.tables import list_to_padded

TARGET_COLUMNS = ("target_id", "year", "material", "hdrf", "calibration", "agc", "x", "y", "z", "radius_m")
DATASET_COLUMNS = ("dataset", "year")


class TargetTableError(WaveforestError):
    """A targets.csv or datasets.csv that does not follow its schema."""


def _read_csv(path: str | Path, required: tuple[str, ...]) -> pd.DataFrame:
    path = Path(path)
    if not path.exists():
        raise TargetTableError(f"{path}: no such file")
    try:
        df = pd.read_csv(path, dtype=str, keep_default_na=False)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise TargetTableError(f"{path}: not a readable CSV table ({exc})") from None
    df.columns = [c.strip() for c in df.columns]
    missing = [c for c in required if c not in df.columns]
    if missing:
        raise TargetTableError(f"{path}: lacks column(s) {', '.join(missing)}")
    return df


def _numeric(df: pd.DataFrame, name: str, path, *, allow_empty: bool = False) -> np.ndarray:
    raw = df[name].astype(str).str.strip()
    empty = raw == ""
    if empty.any() and not allow_empty:
        raise TargetTableError(f"{path}: column {name}, row {int(np.flatnonzero(empty)[0]) + 2}: empty value")
    vals = pd.to_numeric(raw.where(~empty, None), errors="coerce")
    bad = vals.isna() & ~empty
    if bad.any():
        row = int(np.flatnonzero(bad.to_numpy())[0])
        raise TargetTableError(f"{path}: column {name}, row {row + 2}: {raw.iloc[row]!r} is not a number")
    return vals.to_numpy(dtype=np.float64)


def read_targets(path: str | Path) -> pd.DataFrame:
    """Read and check ``targets.csv``; numeric columns as float, flags as bool, year as int."""
    df = _read_csv(path, TARGET_COLUMNS)
    out = pd.DataFrame({"target_id": df["target_id"].astype(str).str.strip(),
                        "material": df["material"].astype(str).str.strip()})
    year = _numeric(df, "year", path)
    if np.any(year != np.round(year)):
        raise TargetTableError(f"{path}: column year must hold integers")
    out["year"] = year.astype(np.int64)
    out["hdrf"] = _numeric(df, "hdrf", path, allow_empty=True)
    for flag in ("calibration", "agc"):
        v = _numeric(df, flag, path)
        if not np.isin(v, (0.0, 1.0)).all():
            raise TargetTableError(f"{path}: column {flag} must be 0 or 1")
        out[flag] = v.astype(bool)
    for c in ("x", "y", "z", "radius_m"):
        out[c] = _numeric(df, c, path)
    if (out["radius_m"] <= 0).any():
        raise TargetTableError(f"{path}: column radius_m must be > 0")
    cal_no_hdrf = out["calibration"] & ~(out["hdrf"] > 0)
    if cal_no_hdrf.any():
        tid = out["target_id"][cal_no_hdrf].iloc[0]
        raise TargetTableError(f"{path}: calibration target {tid!r} needs an HDRF > 0")
    if out["target_id"].duplicated().any():
        raise TargetTableError(f"{path}: target_id values must be unique")
    return out


def read_datasets(path: str | Path) -> pd.DataFrame:
    """Read ``datasets.csv`` (dataset and year required; numeric extras converted when present)."""
    df = _read_csv(path, DATASET_COLUMNS)
    out = pd.DataFrame({"dataset": df["dataset"].astype(str).str.strip()})
    year = _numeric(df, "year", path)
    if np.any(year != np.round(year)):
        raise TargetTableError(f"{path}: column year must hold integers")
    out["year"] = year.astype(np.int64)
    for c in ("mean_range_m", "pulse_width_fwhm_ns", "footprint_diameter_m", "divergence_mrad", "sampling_ns",
              "max_scan_zenith_deg"):
        if c in df.columns:
            out[c] = _numeric(df, c, path, allow_empty=True)
    if out["dataset"].duplicated().any():
        raise TargetTableError(f"{path}: dataset names must be unique")
    return out


def dataset_year(datasets: pd.DataFrame, dataset: str, source: str = "datasets.csv") -> int:
    """The year of ``dataset`` in a datasets table."""
    row = datasets.loc[datasets["dataset"] == dataset]
    if row.empty:
        raise TargetTableError(f"{source}: dataset {dataset!r} is not listed")
    return int(row["year"].iloc[0])


def target_membership(x, y, year: int, targets: pd.DataFrame) -> np.ndarray:
    """Index (row position in ``targets``) of the target each point lies on, -1 for none.

    Parameters
    ----------
    x, y : (n,) float, m (first DR echo positions; NaN = no echo -> -1).
    year : int, the dataset's year (only targets of that year count).
    targets : DataFrame with x, y, radius_m, year.

    Returns
    -------
    (n,) int64
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if x.shape != y.shape or x.ndim != 1:
        raise ValueError("x and y must be 1-D arrays of equal length")
    out = np.full(x.shape, -1, dtype=np.int64)
    cand = np.flatnonzero(targets["year"].to_numpy() == year)
    if cand.size == 0 or x.size == 0:
        return out
    tx = targets["x"].to_numpy(np.float64)[cand]
    ty = targets["y"].to_numpy(np.float64)[cand]
    tr = targets["radius_m"].to_numpy(np.float64)[cand]
    chunk = max(1, 4_000_000 // cand.size)
    for s in range(0, x.size, chunk):  # bounded memory; a handful of chunks, not a loop per pulse
        d2 = (x[s:s + chunk, None] - tx[None, :]) ** 2 + (y[s:s + chunk, None] - ty[None, :]) ** 2
        d2 = np.where(d2 <= tr[None, :] ** 2, d2, np.inf)
        best = np.argmin(d2, axis=1)
        hit = np.isfinite(d2[np.arange(d2.shape[0]), best])
        out[s:s + chunk] = np.where(hit, cand[best], -1)
    return out


def first_echo_xy(pulses: pa.Table) -> tuple[np.ndarray, np.ndarray]:
    """(echo_x[0], echo_y[0]) of every pulse, NaN without echoes."""
    res = []
    for c in ("echo_x", "echo_y"):
        vals, lens = list_to_padded(pulses.column(c), dtype=np.float64)
        v = np.full(pulses.num_rows, np.nan)
        if vals.shape[1]:
            v[lens > 0] = vals[lens > 0, 0]
        res.append(v)
    return res[0], res[1]


def pulse_targets(pulses: pa.Table, targets: pd.DataFrame, year: int) -> np.ndarray:
    """Target index of each pulse of a pulse table (first DR echo within radius), -1 for none."""
    x, y = first_echo_xy(pulses)
    return target_membership(x, y, year, targets)
