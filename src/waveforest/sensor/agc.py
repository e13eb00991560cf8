"""AGC normalisation, Eq. 1 (docs/method.md §(b)).

``I_cal = I_obs / (1 + (AGC - a) b)`` for DR intensities, and for waveforms, sample-wise on
the part above the noise floor:

    V_norm = (V - n0) / (1 + (AGC - a) b) + n0

with n0 the dataset noise mean c-bar from the last ``calibrate.noise_tail`` samples of every
waveform, a the dataset mean AGC, and b fitted per dataset by minimising the pooled
within-target relative SD ("nested CV") of an echo amplitude A over homogeneous targets
(targets.csv rows with agc = 1):

    CV(b) = sqrt( sum_k sum_i (A_ki / mean_i(A_ki) - 1)^2 / (N - K) ),  A_ki = A_raw,ki / g_ki(b)

``agc.statistic`` chooses A_raw. ``peak`` is docs/method.md §(b) word for word: max V - n0. Its
noise part is not gained: the largest of a few noisy samples near the top exceeds the true
peak by about one noise SD whatever the gain, so on weak targets A_raw = g A_0 + delta and the
fit reads g^(1 - delta / A) -- b comes out low by about delta / A (measured errors of both
statistics: docs/validation.md, "AGC fit"). ``energy`` (default) sums V - n0 over
``agc.energy_half_window_ns`` either side of the largest sample: the noise in that window has
zero mean, so the sum scales with the gain exactly and b stays unbiased on weak targets.

k = fit group, i = pulse, N pulses, K groups; a coarse grid over the bounded interval
``agc.b_bounds`` followed by a bounded Brent refinement around the best grid point. The
interval is narrowed so that every pulse keeps a gain of at least :data:`GAIN_MIN`; pulses
whose waveform reaches the digitiser maximum (clipped peaks) are left out of the fit.

The fit groups are target *passes*, not targets: a target flown by two strips is seen at two
ranges (1/R^2 of Eq. 7) and incidence angles (sigma = rho cos(gamma)/pi for a Lambertian
target, plus the peak broadening of an inclined footprint) -- a few % of amplitude -- and,
independently, at two AGC levels, because the loop follows each strip's own terrain. Pooled
over strips, the CV would read that amplitude difference as AGC gain and bias b
(docs/validation.md, "AGC fit"). Within one pass the sensor sees the target from (nearly) one
position: its range varies by r sin(theta) / R < 0.2 % (target radius r <= 5 m, scan zenith
theta <= 15 degrees, R ~ 1 km) and its incidence by less than a degree, far below the noise
of a peak amplitude, so a pass is truly homogeneous and only the AGC changes within it (the
loop's jitter and its reaction to the signal). Passes are told apart by the GPS time: pulses
of one target more than ``agc.pass_gap_s`` apart (default 30 s; an aircraft crosses a target
in < 1 s and turns between strips take ~90 s) belong to different passes (:func:`target_passes`;
the pulse table carries no LAS point_source_id). Each pass is a group of its own
(``agc.min_pulses_per_target`` applies per pass); the per-target counts and CVs in the JSON
report the targets, the per-pass ones the groups.

Pulses with no AGC (NaN) are not normalised (gain 1). A dataset with no AGC at all is passed
through unnormalised with a warning and b = NaN (the AGC is not faked).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np
import pyarrow as pa

import waveforest.sensor.checks as checks
from waveforest.sensor.params import GAIN_MIN

GAIN_COLUMN = "agc_gain"
"""Column appended to a normalised pulse table: the gain g of Eq. 1 applied to each pulse."""


def agc_gain(agc, a: float, b: float) -> np.ndarray:
    """Gain ``1 + (AGC - a) b`` of Eq. 1 (NaN where the AGC is NaN).

    Raises ValueError if a finite gain is <= 0 (b outside its meaningful range).
    """
    g = 1.0 + (np.asarray(agc, dtype=np.float64) - a) * b
    if np.any(g[np.isfinite(g)] <= 0):
        raise ValueError(f"AGC gain 1 + (AGC - a) b <= 0 for a = {a}, b = {b}: b is too large for these AGC values")
    return g


def normalise_intensity(intensity, agc, a: float, b: float) -> np.ndarray:
    """DR intensities normalised by Eq. 1 (unchanged where the AGC is NaN)."""
    return np.asarray(intensity, dtype=np.float64) / checks.gain_or_one(agc_gain(agc, a, b))


def normalise_waveforms(samples, agc, a: float, b: float, n0: float) -> np.ndarray:
    """Waveforms normalised by Eq. 1 above the noise floor: (V - n0)/g + n0.

    Parameters
    ----------
    samples : (n, n_s) DN (NaN padding stays NaN).  agc : (n,) AGC values (NaN: unchanged).
    a, b : Eq. 1.  n0 : noise floor, DN.

    Returns
    -------
    (n, n_s) float32
    """
    return divide_gain(samples, agc_gain(agc, a, b), n0)


def divide_gain(samples, gain, n0: float) -> np.ndarray:
    """(V - n0)/g + n0 per waveform (Eq. 1 with the gains g given; no gain, NaN or <= 0: unchanged), float32 DN."""
    x = np.asarray(samples, dtype=np.float64)
    if x.ndim != 2:
        raise ValueError(f"samples must be 2-D, got shape {x.shape}")
    g = checks.gain_or_one(gain)
    if g.shape != (x.shape[0],):
        raise ValueError(f"gain must have shape ({x.shape[0]},), got {g.shape}")
    return ((x - n0) / g[:, None] + n0).astype(np.float32)


def peak_amplitudes(samples, lengths, n0: float) -> np.ndarray:
    """Largest sample of each waveform minus n0, DN (NaN for empty rows)."""
    x, lens = checks.waveforms(samples, lengths)
    if x.shape[1] == 0:
        return np.full(x.shape[0], np.nan)
    valid = np.arange(x.shape[1])[None, :] < lens[:, None]
    m = np.where(valid, x, -np.inf).max(axis=1).astype(np.float64)
    return np.where(lens > 0, m - n0, np.nan)


def window_sums(samples, lengths, half_window) -> tuple[np.ndarray, np.ndarray]:
    """Sum of the samples within ``half_window`` samples of each waveform's largest one.

    Parameters
    ----------
    samples : (N, M) waveforms, DN.  lengths : (N,) valid samples per row.
    half_window : int or (N,) int, samples either side of the maximum.

    Returns
    -------
    sums : (N,) float64, DN (NaN for empty rows); counts : (N,) int64, samples summed (the
    window clipped to the record). An echo energy above n0 is ``sums - counts * n0``.
    """
    x, lens = checks.waveforms(samples, lengths)
    n, m = x.shape
    half = np.broadcast_to(np.asarray(half_window, dtype=np.int64), (n,))
    if m == 0 or n == 0:
        return np.full(n, np.nan), np.zeros(n, np.int64)
    valid = np.arange(m)[None, :] < lens[:, None]
    k = np.where(valid, x, -np.inf).argmax(axis=1)
    h = int(half.max()) if n else 0
    j = np.arange(-h, h + 1)
    idx = k[:, None] + j[None, :]
    inside = (idx >= 0) & (idx < lens[:, None]) & (np.abs(j)[None, :] <= half[:, None])
    vals = np.take_along_axis(x, np.clip(idx, 0, m - 1), axis=1).astype(np.float64)
    sums = np.where(inside, vals, 0.0).sum(axis=1)
    return np.where(lens > 0, sums, np.nan), inside.sum(axis=1)


def nested_cv(amplitudes, agc, groups, a: float, b: float) -> float:
    """Pooled within-target relative SD of AGC-normalised amplitudes (docs/method.md §(b) suggestion).

    Parameters
    ----------
    amplitudes : (N,) peak amplitudes above n0, DN.  agc : (N,) AGC.  groups : (N,) int target
    labels.  a, b : Eq. 1.

    Returns
    -------
    float, CV(b) = sqrt(sum (A/mean_k - 1)^2 / (N - K)).
    """
    A = np.asarray(amplitudes, dtype=np.float64) / agc_gain(agc, a, b)
    _, inv = np.unique(np.asarray(groups), return_inverse=True)
    K = int(inv.max()) + 1 if inv.size else 0
    N = A.size
    if N - K < 1:
        return float("nan")
    means = np.bincount(inv, weights=A, minlength=K) / np.bincount(inv, minlength=K)
    return float(math.sqrt(np.sum((A / means[inv] - 1.0) ** 2) / (N - K)))


def target_passes(gps_time, targets, gap_s: float) -> np.ndarray:
    """Pass index of each pulse within its target: a new pass wherever the target's pulses are
    more than ``gap_s`` apart in GPS time (a new flight strip over the same target).

    Parameters
    ----------
    gps_time : (N,) float, s (NaN times join the target's last pass; all NaN -> one pass).
    targets : (N,) int target labels.
    gap_s : float > 0, s.

    Returns
    -------
    (N,) int64, 0, 1, ... in time order within each target.
    """
    t = np.asarray(gps_time, dtype=np.float64)
    k = np.asarray(targets)
    if t.shape != k.shape or t.ndim != 1:
        raise ValueError("gps_time and targets must be 1-D arrays of equal length")
    if not gap_s > 0:
        raise ValueError(f"gap_s must be > 0, got {gap_s}")
    out = np.zeros(t.size, dtype=np.int64)
    if t.size == 0:
        return out
    order = np.lexsort((np.where(np.isfinite(t), t, np.inf), k))
    ts, ks = t[order], k[order]
    same = ks[1:] == ks[:-1]
    new_pass = np.concatenate([[False], same & (np.diff(ts) > gap_s)])  # NaN gaps compare False
    cum = np.cumsum(new_pass)
    start = np.concatenate([[True], ~same])  # first pulse of each target
    base = np.maximum.accumulate(np.where(start, cum, 0))
    out[order] = cum - base
    return out


def cv_per_group(amplitudes, agc, groups, a: float, b: float) -> dict:
    """Relative SD of the normalised amplitude within each target: {label: cv}."""
    A = np.asarray(amplitudes, dtype=np.float64) / agc_gain(agc, a, b)
    groups = np.asarray(groups)
    out = {}
    for g in np.unique(groups):  # a handful of targets
        v = A[groups == g]
        out[g.item() if hasattr(g, "item") else g] = float(np.std(v, ddof=1) / np.mean(v)) if v.size > 1 else float("nan")
    return out


def feasible_b_bounds(agc, a: float, bounds: tuple[float, float]) -> tuple[float, float]:
    """``bounds`` narrowed so that 1 + (AGC - a) b >= GAIN_MIN for every finite AGC."""
    v = np.asarray(agc, dtype=np.float64)
    v = v[np.isfinite(v)]
    lo, hi = float(bounds[0]), float(bounds[1])
    if lo > hi:
        raise ValueError(f"b bounds must be (lo, hi) with lo <= hi, got {bounds}")
    if v.size:
        below = a - v.min()  # > 0: pulses below the mean AGC limit positive b
        above = v.max() - a  # > 0: pulses above it limit negative b
        if below > 0:
            hi = min(hi, (1.0 - GAIN_MIN) / below)
        if above > 0:
            lo = max(lo, -(1.0 - GAIN_MIN) / above)
    if lo > hi:
        raise ValueError(f"no b in {bounds} keeps every AGC gain >= {GAIN_MIN}")
    return lo, hi


def fit_b(amplitudes, agc, groups, a: float, bounds=(0.0, 0.05), grid_points: int = 101,
          all_agc=None) -> tuple[float, float, np.ndarray, np.ndarray]:
    """b of Eq. 1 minimising :func:`nested_cv` (a fixed), bounded 1-D search.

    Parameters
    ----------
    amplitudes, agc, groups : (N,) target-pulse peak amplitudes (DN above n0), AGC, labels.
    a : reference AGC (dataset mean).  bounds : (lo, hi) search interval.
    grid_points : coarse grid size before the Brent refinement.
    all_agc : AGC values of the whole dataset, to keep every gain positive (default: ``agc``).

    Returns
    -------
    b, cv_min, b_grid (grid_points,), cv_grid (grid_points,)
    """
    amplitudes = np.asarray(amplitudes, dtype=np.float64)
    agc = np.asarray(agc, dtype=np.float64)
    groups = np.asarray(groups)
    if not (amplitudes.shape == agc.shape == groups.shape) or amplitudes.ndim != 1:
        raise ValueError("amplitudes, agc and groups must be 1-D arrays of equal length")
    ok = np.isfinite(amplitudes) & np.isfinite(agc) & (amplitudes > 0)
    amplitudes, agc, groups = amplitudes[ok], agc[ok], groups[ok]
    if amplitudes.size - np.unique(groups).size < 2:
        raise ValueError("fit_b: too few target pulses to fit b")
    lo, hi = feasible_b_bounds(agc if all_agc is None else all_agc, a, bounds)
    grid = np.linspace(lo, hi, max(int(grid_points), 3))
    curve = np.array([nested_cv(amplitudes, agc, groups, a, b) for b in grid])  # grid_points evaluations
    k = int(np.nanargmin(curve))
    lo_r, hi_r = grid[max(k - 1, 0)], grid[min(k + 1, grid.size - 1)]
    if hi_r > lo_r:
        from scipy.optimize import minimize_scalar

        res = minimize_scalar(lambda b: nested_cv(amplitudes, agc, groups, a, b), bounds=(lo_r, hi_r),
                              method="bounded", options={"xatol": 1e-9 * max(1.0, abs(hi - lo))})
        b_best, cv_best = (float(res.x), float(res.fun)) if res.fun <= curve[k] else (float(grid[k]), float(curve[k]))
    else:
        b_best, cv_best = float(grid[k]), float(curve[k])
    return b_best, cv_best, grid, curve


@dataclass
class AGCFit:
    """The AGC fit of one dataset (written as the ``agc`` step's JSON)."""

    dataset: str
    year: int | None
    a: float
    b: float
    n0: float
    noise_sd: float
    b_bounds: tuple[float, float]
    cv_before: float
    cv_after: float
    n_pulses_total: int
    n_fit_pulses: int
    n_missing_agc: int
    n_saturated: int
    n_per_target: dict = field(default_factory=dict)
    cv_per_target_before: dict = field(default_factory=dict)
    cv_per_target_after: dict = field(default_factory=dict)
    pass_gap_s: float = float("nan")
    n_per_pass: dict = field(default_factory=dict)
    cv_per_pass_before: dict = field(default_factory=dict)
    cv_per_pass_after: dict = field(default_factory=dict)
    b_grid: list = field(default_factory=list)
    cv_grid: list = field(default_factory=list)
    fixed_b: bool = False
    statistic: str = "peak"

    def to_dict(self) -> dict:
        d = asdict(self)
        d["b_bounds"] = list(self.b_bounds)
        return d


def _scale_list_column(col: pa.ChunkedArray, gain: np.ndarray, n0: float) -> pa.ListArray:
    """A list<float32> column with each row mapped v -> (v - n0)/gain[row] + n0."""
    arr = col.combine_chunks() if isinstance(col, pa.ChunkedArray) else col
    offsets = arr.offsets.to_numpy().astype(np.int64)
    values = arr.flatten().to_numpy(zero_copy_only=False).astype(np.float64)
    lens = np.diff(offsets)
    g = np.repeat(gain, lens)
    new = ((values - n0) / g + n0).astype(np.float32)
    return pa.ListArray.from_arrays(pa.array(offsets - offsets[0], type=pa.int32()), pa.array(new, type=pa.float32()))


def normalise_pulses(pulses: pa.Table, a: float, b: float, n0: float) -> pa.Table:
    """A pulse table with waveforms and DR intensities normalised by Eq. 1.

    Adds the column :data:`GAIN_COLUMN` (the gain applied; 1 where the AGC is NaN or b is NaN).
    """
    agc = pulses.column("agc").to_numpy(zero_copy_only=False).astype(np.float64)
    if np.isfinite(a) and np.isfinite(b):
        g = checks.gain_or_one(agc_gain(agc, a, b))
    else:
        g = np.ones(pulses.num_rows)
    out = pulses
    for name, level in (("samples", n0), ("echo_intensity", 0.0)):
        i = out.schema.get_field_index(name)
        out = out.set_column(i, name, _scale_list_column(out.column(name), g, level))
    if GAIN_COLUMN in out.column_names:
        out = out.drop_columns([GAIN_COLUMN])
    return out.append_column(GAIN_COLUMN, pa.array(g, type=pa.float64()))


SCAN_COLUMNS = ["dataset", "gps_time", "agc", "echo_x", "echo_y", "samples", "sampling_ns"]
"""Pulse-table columns the first pass of the ``agc`` stage reads (AGC values, noise, targets)."""
