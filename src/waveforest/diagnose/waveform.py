"""Whole-waveform statistics: the evidence beyond the first echo, one row per pulse.

docs/method.md §(j) (the gap). Per pulse, from its waveform samples v_k (DN, sample k at
k * sampling_ns from the first sample), the calibrated noise mean m and SD s of its dataset
and its first-echo features (:func:`waveforest.sensor.feature_table`):

* the noise-gated signal ``e_k = v_k - m`` where ``v_k - m > GATE_SD * s``, else 0, and its
  sum ``E_w`` over the record (the waveform's energy above the noise);
* sample heights above the ground ``h_k = anchor_z + dir_z * k * dt * c/2 - ground_z`` (m);
* the **energy profile by height**: the shares of ``E_w`` in the height bins of
  :data:`HEIGHT_EDGES_M` (``E_h0`` the ground and the first 0.25 m, ``E_h1`` 0.25-0.75 m,
  ``E_h2`` 0.75-1.5 m, ``E_h3`` 1.5-3 m, ``E_h4`` above 3 m; they sum to 1);
* ``E_below``: the share of ``E_w`` more than :data:`BELOW_M` below the first echo (along z,
  past the first echo's own pulse): the energy below the first echo;
* ``D_mean``: the energy-weighted mean depth of the signal below the first echo (m along z,
  ``echo_z - z_k``, ``E_w``-weighted);
* ``H_median``: the height above the ground above which half of ``E_w`` lies (m): where the
  energy returns, pulled down by an understory, up by a denser crown. (The last local maximum
  is no measure of the lowest return: the system waveform rings 1-3 m below the ground return,
  and noise peaks lie tens of metres below.)

Shares and depths are ratios within one pulse, so the AGC gain and the pulse energy cancel;
they stand beside the first-echo features in the gap (:data:`WAVEFORM_FEATURES`, SD floors
:data:`WAVEFORM_SD_FLOOR`). NaN where a pulse has no sample above the gate.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc

from waveforest.constants import RANGE_PER_NS
from waveforest.errors import WaveforestError
from waveforest.io.pulses import list_to_padded

HEIGHT_EDGES_M: tuple[float, ...] = (0.25, 0.75, 1.5, 3.0)
"""Edges (m above the ground) between the height bins of the energy profile."""

PROFILE_FEATURES: tuple[str, ...] = tuple(f"E_h{k}" for k in range(len(HEIGHT_EDGES_M) + 1))
"""Energy shares by height bin, ground first."""

WAVEFORM_FEATURES: tuple[str, ...] = PROFILE_FEATURES + ("E_below", "D_mean", "H_median")
"""Whole-waveform statistics (module docstring), in report order."""

WAVEFORM_SD_FLOOR: dict[str, float] = {**{f: 0.01 for f in PROFILE_FEATURES}, "E_below": 0.01,
                                       "D_mean": 0.05, "H_median": 0.05}
"""Smallest meaningful SD of each statistic: 1 % of the energy; 0.05 m (the CFD's timing precision)."""

GATE_SD = 3.0
"""A sample counts as signal above this many noise SDs over the noise mean."""

BELOW_M = 1.0
"""``E_below`` counts the energy more than this far below the first echo, m (past its own pulse,
whose FWHM of 4-6 ns spans 0.3-0.45 m)."""

_NEEDED = ("dataset", "pulse_id", "samples", "sampling_ns", "anchor_z", "dir_z", "ground_z")


def waveform_statistics(pulses: pa.Table, noise: Mapping, first: pd.DataFrame) -> pd.DataFrame:
    """The statistics of the module docstring for every pulse of ``pulses``.

    Parameters
    ----------
    pulses : pa.Table
        Pulse table rows (:mod:`waveforest.io.pulses`) with ``ground_z`` (``select`` columns).
    noise : mapping dataset -> calibration dict
        ``noise_mean`` and ``noise_sd`` (DN) of each dataset of ``pulses``.
    first : DataFrame
        One row per row of ``pulses``, same order, with ``echo_z`` (m): the height of the
        pulse's first echo (NaN: none).

    Returns
    -------
    DataFrame
        dataset, pulse_id and :data:`WAVEFORM_FEATURES`, one row per pulse, same order.
    """
    missing = [c for c in _NEEDED if c not in pulses.column_names]
    if missing:
        raise WaveforestError(f"waveform statistics: pulse table without column(s) {', '.join(missing)}")
    if len(first) != pulses.num_rows:
        raise WaveforestError(f"waveform statistics: {len(first)} first-echo rows for {pulses.num_rows} pulses")
    n = pulses.num_rows
    if n == 0:
        return pd.DataFrame({c: pd.Series(dtype=float) for c in ("dataset", "pulse_id") + WAVEFORM_FEATURES})
    ds = np.asarray(pulses.column("dataset").to_numpy(zero_copy_only=False), dtype=object)
    mean, sd = np.empty(n), np.empty(n)
    for name in pd.unique(ds):
        if name not in noise:
            raise WaveforestError(f"waveform statistics: no noise estimate (calibration) of dataset {name}")
        m = ds == name
        mean[m], sd[m] = float(noise[name]["noise_mean"]), float(noise[name]["noise_sd"])
    x, lens = list_to_padded(pulses.column("samples"))
    col = lambda c: pulses.column(c).to_numpy(zero_copy_only=False).astype(np.float64)  # noqa: E731
    dt, az, dz, gz = col("sampling_ns"), col("anchor_z"), col("dir_z"), col("ground_z")
    k = np.arange(x.shape[1], dtype=np.float64)[None, :]
    t = k * dt[:, None]  # ns from the first sample
    z = az[:, None] + dz[:, None] * t * RANGE_PER_NS
    v = x.astype(np.float64) - mean[:, None]
    inside = k < lens[:, None]
    e = np.where(inside & (v > GATE_SD * sd[:, None]), v, 0.0)
    total = e.sum(axis=1)
    ok = total > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        share = lambda w: np.where(ok, (e * w).sum(axis=1) / total, np.nan)  # noqa: E731
        h = z - gz[:, None]
        b = np.digitize(h, HEIGHT_EDGES_M)
        out = {f: share(b == j) for j, f in enumerate(PROFILE_FEATURES)}
        echo_z = first["echo_z"].to_numpy(np.float64)
        out["E_below"] = np.where(np.isfinite(echo_z), share(z < echo_z[:, None] - BELOW_M), np.nan)
        out["D_mean"] = np.where(np.isfinite(echo_z), share(echo_z[:, None] - z), np.nan)
        half = np.argmax(np.cumsum(e, axis=1) >= 0.5 * total[:, None], axis=1)
        out["H_median"] = np.where(ok, h[np.arange(n), half], np.nan)
    res = pd.DataFrame({"dataset": ds, "pulse_id": col("pulse_id").astype(np.int64)})
    for f in WAVEFORM_FEATURES:
        res[f] = out[f]
    return res


def with_waveform_statistics(features: pd.DataFrame, pulses: dict, noise: Mapping) -> pd.DataFrame:
    """``features`` (rows with dataset, pulse_id, echo_z) with the statistics of
    their pulses' waveforms added, from ``pulses`` (dataset -> pulse table holding those
    pulse ids, e.g. the ``select`` tables) and ``noise`` (dataset -> calibration dict).
    Columns of :data:`WAVEFORM_FEATURES` already present are replaced."""
    base = features.drop(columns=[c for c in WAVEFORM_FEATURES if c in features.columns])
    parts = []
    for ds, rows in base.groupby(base["dataset"].astype(str), sort=True):
        if ds not in pulses:
            raise WaveforestError(f"waveform statistics: no pulse table of dataset {ds}")
        table = pulses[ds]
        ids = rows["pulse_id"].to_numpy(np.int64)
        sub = table.filter(pc.is_in(table.column("pulse_id"), value_set=pa.array(np.unique(ids))))
        have = sub.column("pulse_id").to_numpy()
        order = np.argsort(have, kind="stable")
        uniq = have[order]
        if len(np.unique(have)) != len(have):
            raise WaveforestError(f"waveform statistics: dataset {ds}: a pulse_id twice in the pulse table")
        pos = np.searchsorted(uniq, ids)
        if np.any(pos >= len(uniq)) or np.any(uniq[np.minimum(pos, len(uniq) - 1)] != ids):
            raise WaveforestError(f"waveform statistics: dataset {ds}: feature rows without a pulse in the table")
        sub = sub.take(pa.array(order[pos]))
        stats = waveform_statistics(sub, noise, rows[["echo_z"]].reset_index(drop=True))
        parts.append(pd.concat([rows.reset_index(drop=True), stats[list(WAVEFORM_FEATURES)]], axis=1))
    return pd.concat(parts, ignore_index=True) if parts else features
