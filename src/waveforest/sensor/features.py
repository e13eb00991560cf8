"""First-echo waveform features (docs/method.md §(h)), the same code for real and simulated pulses.

For each waveform, with c-bar the noise mean and SD its SD (dataset values):

- segment: the contiguous run of samples above ``c-bar + segment_sd * SD`` that contains the
  first echo (the sample nearest the echo time; if that one is not above the threshold, the
  nearest sample above it within ``echo_search_ns``); no such sample -> NaN features;
- Apeak = max(V) - c-bar over the segment, DN (the highest sample);
- E = sum(V - c-bar) * dt / 1 ns over the segment, DN (the sample sum at 1-ns sampling);
- FWHM = distance between the half-maximum crossings found from the peak sample outward,
  each by linear interpolation between the two samples that straddle it, ns (NaN if the
  record ends first). The level is half the peak of the parabola through the highest sample
  and its neighbours (the sampled maximum lies below the true peak by up to ~1.5 % for a
  4-ns pulse at 1-ns sampling, which would widen the FWHM by as much); Apeak itself stays
  the highest sample, the digitised value of the paper;
- Npeaks = local maxima of the segment that rise at least ``peak_rise_sd * SD`` above the
  adjacent minima on both sides (hysteresis; the segment ends count as minima at the
  threshold level), at least 1 for any segment;
- H (in :func:`feature_table`) = height of the echo above the sample's ground:
  ``anchor_z + dir_z * t_echo * RANGE_PER_NS - ground_z``, m.

The echo time is the pulse's first echo: ``echo_time_ns[0]`` of the pulse table (real: the
sensor's first DR echo; simulated: the first CFD echo, stored the same way by ``simulate``).
A pulse without one gets the first CFD echo of its own waveform.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping

import numpy as np
import pandas as pd
import pyarrow as pa
from numba import njit, prange

import waveforest.sensor.checks as checks
from waveforest.constants import RANGE_PER_NS
from waveforest.errors import WaveforestWarning
from waveforest.io.pulses import PULSE_SCHEMA, list_to_padded
from waveforest.sensor.agc import GAIN_COLUMN
from waveforest.sensor.cfd import detect_echoes
from waveforest.sensor.decompose import decompose
from waveforest.sensor.noise import NoiseStats
from waveforest.sensor.params import ECHO_SEARCH_NS, CFDParams, FeatureParams

FEATURE_NAMES = ("Npeaks", "Apeak", "FWHM", "E")
"""The radiometric/shape features of docs/method.md §(h) (H is geometric, added by feature_table)."""


@njit(cache=True)
def _features_one(row, n, dt, mean, sd, t_echo, seg_sd, rise_sd, search_ns, out):
    """Features of one waveform into ``out`` = [Npeaks, Apeak, FWHM, E, seg_start, seg_end, t_peak]."""
    for q in range(7):
        out[q] = np.nan
    out[0] = 0.0
    if n < 1 or not math.isfinite(t_echo):
        return
    thr = mean + seg_sd * sd
    ke = int(math.floor(t_echo / dt + 0.5))
    ke = min(max(ke, 0), n - 1)
    if not row[ke] > thr:
        reach = max(1, int(math.floor(search_ns / dt + 1e-9)))
        found = -1
        for d in range(1, reach + 1):
            if ke - d >= 0 and row[ke - d] > thr:
                found = ke - d
                break
            if ke + d < n and row[ke + d] > thr:
                found = ke + d
                break
        if found < 0:
            return
        ke = found
    a = ke
    while a > 0 and row[a - 1] > thr:
        a -= 1
    b = ke
    while b < n - 1 and row[b + 1] > thr:
        b += 1
    kp = a
    energy = 0.0
    for k in range(a, b + 1):
        energy += row[k] - mean
        if row[k] > row[kp]:
            kp = k
    apeak = row[kp] - mean
    # FWHM: crossings of half the (parabolically interpolated) peak, outward from the peak sample
    top = row[kp]
    t_top = kp * dt
    if 0 < kp < n - 1:
        c2 = row[kp - 1] - 2.0 * row[kp] + row[kp + 1]
        if c2 < 0.0:
            off = 0.5 * (row[kp - 1] - row[kp + 1]) / c2
            top = row[kp] - 0.25 * (row[kp - 1] - row[kp + 1]) * off
            t_top = (kp + off) * dt
    half = 0.5 * (mean + top)
    fwhm = np.nan
    kl = kp
    while kl > 0 and row[kl] > half:
        kl -= 1
    kr = kp
    while kr < n - 1 and row[kr] > half:
        kr += 1
    if row[kl] <= half and row[kr] <= half:
        tl = (kl + (half - row[kl]) / (row[kl + 1] - row[kl])) * dt
        tr = (kr - 1 + (half - row[kr - 1]) / (row[kr] - row[kr - 1])) * dt
        fwhm = tr - tl
    # Npeaks: hysteresis peak count, segment ends at threshold level
    r = rise_sd * sd
    npk = 0
    mx = -np.inf
    mn = thr
    look_max = False
    for k in range(a, b + 1):
        v = row[k]
        if look_max:
            if v > mx:
                mx = v
            elif v < mx - r:
                npk += 1
                look_max = False
                mn = v
        else:
            if v < mn:
                mn = v
            elif v > mn + r:
                look_max = True
                mx = v
    if look_max and mx - thr > r:
        npk += 1
    out[0] = max(npk, 1)
    out[1] = apeak
    out[2] = fwhm
    out[3] = energy * dt
    out[4] = a * dt
    out[5] = b * dt
    out[6] = t_top


@njit(parallel=True, cache=True, nogil=True)
def _features_kernel(samples, lengths, dt, mean, sd, t_echo, seg_sd, rise_sd, search_ns, out):
    """Features of every waveform (prange over pulses): out (n, 7)."""
    for i in prange(samples.shape[0]):
        _features_one(samples[i], lengths[i], dt[i], mean[i], sd[i], t_echo[i], seg_sd, rise_sd,
                      search_ns, out[i])


def first_echo_features(samples, lengths, sampling_ns, echo_time_ns, noise_mean, noise_sd,
                        segment_sd: float = 3.0, peak_rise_sd: float = 2.0, *,
                        echo_search_ns: float | None = None) -> dict[str, np.ndarray]:
    """First-echo features of a table of waveforms (docs/method.md §(h)).

    Parameters
    ----------
    samples : (n, n_s) DN, NaN-padded beyond ``lengths``.  lengths : (n,) int or None.
    sampling_ns : float or (n,), ns.  echo_time_ns : (n,) ns from the first sample (NaN: none).
    noise_mean, noise_sd : float or (n,), DN.
    segment_sd, peak_rise_sd : float, in noise SDs.  echo_search_ns : float, ns (default 2).

    Returns
    -------
    dict of (n,) arrays: Npeaks (int16), Apeak (DN), FWHM (ns), E (DN), seg_start_ns,
    seg_end_ns, t_peak_ns (vertex of the peak parabola; ns from the first sample). NaN (Npeaks 0) without a segment.
    """
    p = FeatureParams(segment_sd, peak_rise_sd, ECHO_SEARCH_NS if echo_search_ns is None else echo_search_ns)
    x, lens = checks.waveforms(samples, lengths)
    n = x.shape[0]
    dt = checks.per_pulse(sampling_ns, n, "sampling_ns", positive=True)
    te = checks.per_pulse(echo_time_ns, n, "echo_time_ns", allow_nan=True)
    mean = checks.per_pulse(noise_mean, n, "noise_mean")
    sd = checks.per_pulse(noise_sd, n, "noise_sd", nonnegative=True)
    out = np.empty((n, 7))
    if n:
        _features_kernel(x, lens, dt, mean, sd, te, float(p.segment_sd), float(p.peak_rise_sd),
                         float(p.echo_search_ns), out)
    return {
        "Npeaks": out[:, 0].astype(np.int16), "Apeak": out[:, 1], "FWHM": out[:, 2], "E": out[:, 3],
        "seg_start_ns": out[:, 4], "seg_end_ns": out[:, 5], "t_peak_ns": out[:, 6],
    }


def _first(col: pa.ChunkedArray | pa.Array, n: int) -> np.ndarray:
    """First element of each list (NaN for empty lists), float64."""
    vals, lens = list_to_padded(col, dtype=np.float64)
    out = np.full(n, np.nan)
    if vals.shape[1]:
        out[lens > 0] = vals[lens > 0, 0]
    return out


def _noise_of(noise: Mapping, dataset: str) -> tuple[float, float, float | None]:
    """(mean, sd, fwhm_ns) of a dataset from a mapping of calibration dicts or tuples."""
    if dataset not in noise:
        raise ValueError(f"no noise estimate for dataset {dataset!r} (have: {', '.join(map(str, noise)) or 'none'})")
    v = noise[dataset]
    if isinstance(v, Mapping):
        return float(v["noise_mean"]), float(v["noise_sd"]), v.get("fwhm_ns")
    if isinstance(v, NoiseStats):
        return float(v.mean), float(v.sd), None
    mean, sd = v[0], v[1]
    return float(mean), float(sd), (v[2] if len(v) > 2 else None)


DECOMPOSITION_FEATURES = ("gd_n", "gd_E", "gd_later_A", "gd_depth", "gd_last_H")
"""Multi-echo features of the Gaussian decomposition (docs/method.md §(f2)), per pulse: echo count,
total energy (DN ns), summed amplitude of the echoes after the first (DN), distance from the
first to the last echo along z (m, 0 for one echo) and the last echo's height above the ground (m).
A pulse without an echo has count 0 and the others 0, except gd_last_H (NaN)."""


def decomposition_columns(samples, lens, dt, mean, sd, fwhm_ns, anchor_z, dir_z, ground, agc_gain=None) -> dict:
    """:data:`DECOMPOSITION_FEATURES` of a table of waveforms ((n,) arrays each; ``fwhm_ns``:
    the system pulse FWHM or None; ``agc_gain``: the gains of AGC-normalised waveforms, or None)."""
    d = decompose(samples, lens, dt, mean, sd, pulse_fwhm_ns=fwhm_ns, agc_gain=agc_gain)
    k = d.n_echoes.astype(np.int64)
    has = k > 0
    rows = np.arange(len(k))
    last_t = np.where(has, d.time_ns[rows, np.maximum(k - 1, 0)], np.nan)
    first_t = d.time_ns[:, 0]
    dz = RANGE_PER_NS * np.abs(dir_z)
    later = np.nansum(d.amplitude, axis=1) - np.where(has, d.amplitude[:, 0], 0.0)
    return {
        "gd_n": k.astype(np.int16),
        "gd_E": np.nansum(d.energy, axis=1),
        "gd_later_A": later,
        "gd_depth": np.where(has, (last_t - first_t) * dz, 0.0),
        "gd_last_H": anchor_z + dir_z * last_t * RANGE_PER_NS - ground,
    }


PASS_THROUGH = ("sample_id", "species", "functional_group", "ground_z")
"""Columns added by ``select`` that a feature table keeps when present."""


def feature_table(pulses: pa.Table, noise: Mapping, params: FeatureParams | None = None, *,
                  cfd: CFDParams | Mapping | None = None, range_corrections: Mapping | None = None) -> pd.DataFrame:
    """First-echo features of every pulse of a pulse table (real or simulated alike).

    Parameters
    ----------
    pulses : pa.Table with the pulse schema (:mod:`waveforest.io.pulses`), optionally the ``select`` columns.
    noise : mapping dataset -> calibration dict (noise_mean, noise_sd[, fwhm_ns]) or
        (mean, sd[, fwhm_ns]) tuple or NoiseStats.
    params : FeatureParams.  cfd : CFDParams, or a mapping dataset -> CFDParams, for pulses
        without an echo time (their own first CFD echo; needs fwhm_ns in ``noise`` unless resolved).
    range_corrections : mapping dataset -> RangeCorrection applied to those own CFD echoes.

    Returns
    -------
    pandas.DataFrame, one row per pulse: dataset, pulse_id, source, the select columns present
    (sample_id, species, functional_group, ground_z) and any other scalar extra columns,
    n_echoes, echo_time_ns, Npeaks, Apeak, FWHM, E, H, echo_z, seg_start_ns, seg_end_ns.
    """
    params = params or FeatureParams()
    n = pulses.num_rows
    samples, lens = list_to_padded(pulses.column("samples"))
    datasets = np.asarray(pulses.column("dataset").to_numpy(zero_copy_only=False), dtype=object)
    dt = pulses.column("sampling_ns").to_numpy(zero_copy_only=False).astype(np.float64)
    t_echo = _first(pulses.column("echo_time_ns"), n)
    mean = np.empty(n)
    sd = np.empty(n)
    widths = {}
    for name in pd.unique(datasets):
        m = datasets == name
        mean[m], sd[m], fwhm = _noise_of(noise, name)
        widths[name] = fwhm
        missing = m & ~np.isfinite(t_echo) & (lens > 0)
        if missing.any():

            c = ((cfd.get(name) if isinstance(cfd, Mapping) else cfd) or CFDParams()).resolved(fwhm)
            idx = np.flatnonzero(missing)
            ech = detect_echoes(samples[idx], lens[idx], dt[idx], mean[idx], sd[idx], c, max_echoes=1,
                                range_correction=(range_corrections or {}).get(name))
            t_echo[idx] = ech.times_ns[:, 0]
            warnings.warn(f"dataset {name}: {idx.size} pulse(s) without an echo time; their first CFD echo is used",
                          WaveforestWarning, stacklevel=2)
    if n and samples.shape[1] == 0:
        samples = np.zeros((n, 1), dtype=np.float32)
    feats = first_echo_features(samples, lens, dt, t_echo, mean, sd, params.segment_sd, params.peak_rise_sd,
                                echo_search_ns=params.echo_search_ns)
    col = lambda name: pulses.column(name).to_numpy(zero_copy_only=False).astype(np.float64)  # noqa: E731
    echo_z = col("anchor_z") + col("dir_z") * t_echo * RANGE_PER_NS
    out = {
        "dataset": datasets,
        "pulse_id": pulses.column("pulse_id").to_numpy(zero_copy_only=False).astype(np.int64),
        "source": np.asarray(pulses.column("source").to_numpy(zero_copy_only=False), dtype=object),
    }
    extra = [f for f in pulses.schema if f.name not in PULSE_SCHEMA.names]
    scalar = [f.name for f in extra if not (pa.types.is_list(f.type) or pa.types.is_large_list(f.type))]
    names = [c for c in PASS_THROUGH if c in scalar] + [c for c in scalar if c not in PASS_THROUGH]
    for name in names:  # the select columns first, then any other scalar extras
        out[name] = pulses.column(name).to_numpy(zero_copy_only=False)
    ground = out["ground_z"].astype(np.float64) if "ground_z" in out else np.full(n, np.nan)
    out.update({
        "n_echoes": pulses.column("n_echoes").to_numpy(zero_copy_only=False).astype(np.int16),
        "echo_time_ns": t_echo,
        "Npeaks": feats["Npeaks"], "Apeak": feats["Apeak"], "FWHM": feats["FWHM"], "E": feats["E"],
        "H": echo_z - ground,
        "echo_z": echo_z,
        "seg_start_ns": feats["seg_start_ns"], "seg_end_ns": feats["seg_end_ns"],
    })
    if params.decomposition:
        gd = {f: np.zeros(n, np.int16 if f == "gd_n" else np.float64) for f in DECOMPOSITION_FEATURES}
        gain = col(GAIN_COLUMN) if GAIN_COLUMN in pulses.column_names else np.ones(n)
        for name, fwhm in widths.items():
            m = np.flatnonzero(datasets == name)
            cols = decomposition_columns(samples[m], lens[m], dt[m], mean[m], sd[m], fwhm, col("anchor_z")[m],
                                         col("dir_z")[m], ground[m], gain[m])
            for f in DECOMPOSITION_FEATURES:
                gd[f][m] = cols[f]
        out.update(gd)
    return pd.DataFrame(out)


