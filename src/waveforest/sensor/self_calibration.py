"""Noise, system pulse width and CFD from a pulse table alone (``waveforest tune-cfd``).

A user with one waveform file and no calibration targets still has the sensor's own DR echoes
in every pulse. The paper tuned its CFD "by running it on real WFs ... and comparing with the
real DR ranges: |dR| < 0.10 m for > 95 % of pulses, no bias" (docs/method.md §(f)); this module
gives what that needs from the pulses themselves:

- **noise** (:func:`tail_noise`): the last ``tail`` samples of each pulse, less those within
  ``guard_ns`` after its last DR echo (the echo's own tail and afterpulses), pooled; samples
  beyond ``clip_sd`` SDs of the pooled mean are dropped (iterated: weak echoes that the sensor
  did not report), and the mean and SD of the rest are the noise;
- **system pulse FWHM** (:func:`system_fwhm`): the FWHM (§(h)) of strong single echoes (one DR
  echo, one peak, no flat top) at their DR time; the system pulse is the narrowest a real echo
  can be, so the estimate is the mode of the narrower half of those widths (planar surfaces:
  ground, roofs, roads), found on a histogram smoothed by a Gaussian of the widths' own
  spread;
- **CFD** (fraction, delay, range correction): :func:`waveforest.sensor.cfd_tuning.tune_cfd`,
  the grid and width-class rule that ``calibrate`` uses, run on these pulses;
- **the paper's check** (:func:`dr_agreement`): the share of pulses with a DR echo whose own
  first CFD echo, after the range correction, lies within 0.10 m of the first DR echo, over
  all such pulses (no gate), with the reasons of the rest (no CFD echo; a DR echo the waveform
  does not show above the arming level; the CFD on another echo; the same echo, off by
  0.10-1 m).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

import waveforest.sensor.checks as checks
from waveforest.constants import RANGE_PER_NS
from waveforest.sensor.noise import NoiseStats, tail_samples
from waveforest.sensor.params import CFD_CHECK_M, INTEGER_TOL, QUANTISATION_VAR, RANGE_GATE_M

CLIP_ITERATIONS = 5
"""Rounds of the sigma clipping of :func:`tail_noise` (it converges in two or three)."""

WIDTH_BIN_NS = 0.05
"""Histogram bin of :func:`system_fwhm`, ns."""


def tail_noise(samples, lengths, sampling_ns, last_echo_ns, *, tail: int = 50, guard_ns: float = 20.0,
               clip_sd: float = 4.0) -> NoiseStats:
    """Noise mean and SD from the pulses' own last samples (module docstring).

    Parameters
    ----------
    samples : (n, n_s) DN, NaN-padded beyond ``lengths``.  lengths : (n,).
    sampling_ns : float or (n,), ns.  last_echo_ns : (n,) time of the last DR echo from the
        first sample, ns (NaN: no echo, the whole tail is used).
    tail : samples per pulse at most.  guard_ns : samples earlier than the last echo + this are
        left out, ns.  clip_sd : samples beyond this many SDs of the mean are left out.

    Returns
    -------
    NoiseStats (``n_samples``, ``n_pulses``: what was kept).

    Raises
    ------
    ValueError
        Fewer than 2 samples left.
    """
    x, lens = checks.waveforms(samples, lengths)
    n = x.shape[0]
    dt = checks.per_pulse(sampling_ns, n, "sampling_ns", positive=True)
    last = checks.per_pulse(last_echo_ns, n, "last_echo_ns", allow_nan=True)
    vals, ok = tail_samples(x, lens, tail)
    k = lens[:, None] - tail + np.arange(tail)[None, :]
    ok &= ~(k * dt[:, None] < (last + guard_ns)[:, None])  # NaN last echo: nothing to guard
    ok &= np.isfinite(vals)
    keep = ok.copy()
    for _ in range(CLIP_ITERATIONS):
        v = vals[keep]
        if v.size < 2:
            break
        mean, sd = float(v.mean()), float(v.std(ddof=1))
        new = ok & (np.abs(vals - mean) <= clip_sd * max(sd, math.sqrt(QUANTISATION_VAR)))
        if np.array_equal(new, keep):
            break
        keep = new
    v = vals[keep]
    if v.size < 2:
        raise ValueError(f"tail_noise: fewer than 2 noise samples left (n = {v.size}); the records end too soon "
                         f"after their last echo (tail {tail} samples, guard {guard_ns} ns)")
    mean, sd = float(v.mean()), float(v.std(ddof=1))
    quantised = bool(np.all(np.abs(v - np.round(v)) < INTEGER_TOL))
    sd_analog = math.sqrt(max(sd**2 - QUANTISATION_VAR, 0.0)) if quantised else sd
    dev = np.where(keep, vals - mean, 0.0)
    pair = keep[:, :-1] & keep[:, 1:]
    den = float(np.sum(dev**2))
    lag1 = float(np.sum(np.where(pair, dev[:, :-1] * dev[:, 1:], 0.0)) / den) if den > 0 else 0.0
    return NoiseStats(mean, sd, sd_analog, int(v.size), int(np.count_nonzero(keep.any(axis=1))), lag1, quantised)


@dataclass(frozen=True)
class SystemWidth:
    """The system pulse FWHM estimated from single echoes (:func:`system_fwhm`).

    fwhm_ns : float, ns (NaN if too few echoes).  n_echoes : strong single echoes used.
    spread_ns : robust SD of their widths (1.4826 MAD), ns.
    """

    fwhm_ns: float
    n_echoes: int
    spread_ns: float


def single_echo_mask(fwhm_ns, apeak, npeaks, n_dr_echoes, flat_top, noise_sd, min_snr: float) -> np.ndarray:
    """Strong single echoes: one DR echo, one peak (§(h) Npeaks), no flat top (clipping),
    a finite FWHM and Apeak >= ``min_snr`` noise SDs."""
    w = np.asarray(fwhm_ns, dtype=np.float64)
    return (np.isfinite(w) & (w > 0) & (np.asarray(npeaks) == 1) & (np.asarray(n_dr_echoes) == 1)
            & ~np.asarray(flat_top, dtype=bool) & (np.asarray(apeak, dtype=np.float64) >= min_snr * noise_sd))


def system_fwhm(widths_ns, *, min_echoes: int = 20) -> SystemWidth:
    """Mode of the narrower half of single-echo widths, ns (module docstring).

    The histogram (bins of :data:`WIDTH_BIN_NS`) is smoothed by a Gaussian of SD
    max(robust SD of the narrower half, one bin); its highest point is the estimate.
    """
    w = np.sort(np.asarray(widths_ns, dtype=np.float64)[np.isfinite(widths_ns)])
    if w.size < min_echoes:
        return SystemWidth(math.nan, int(w.size), math.nan)
    spread = float(1.4826 * np.median(np.abs(w - np.median(w))))
    narrow = w[: max(min_echoes, w.size // 2)]
    h = max(float(1.4826 * np.median(np.abs(narrow - np.median(narrow)))), WIDTH_BIN_NS)
    lo, hi = narrow[0] - 3 * h, narrow[-1] + 3 * h
    edges = np.arange(lo, hi + WIDTH_BIN_NS, WIDTH_BIN_NS)
    counts, _ = np.histogram(narrow, edges)
    half = int(math.ceil(4 * h / WIDTH_BIN_NS))
    kernel = np.exp(-0.5 * (np.arange(-half, half + 1) * WIDTH_BIN_NS / h) ** 2)
    smooth = np.convolve(counts, kernel, mode="same")
    centre = 0.5 * (edges[:-1] + edges[1:])
    return SystemWidth(float(centre[int(np.argmax(smooth))]), int(w.size), spread)


def flat_top(samples, lengths) -> np.ndarray:
    """(n,) bool: the waveform's highest sample is the highest of all waveforms given and
    repeats in the next or previous sample (a digitiser or detector clipped the echo)."""
    x, lens = checks.waveforms(samples, lengths)
    n = x.shape[0]
    if n == 0 or x.shape[1] == 0:
        return np.zeros(n, bool)
    valid = np.arange(x.shape[1])[None, :] < lens[:, None]
    xv = np.where(valid, x, -np.inf)
    kp = np.argmax(xv, axis=1)
    top = xv[np.arange(n), kp]
    prev = xv[np.arange(n), np.maximum(kp - 1, 0)]
    nxt = xv[np.arange(n), np.minimum(kp + 1, x.shape[1] - 1)]
    repeated = ((kp > 0) & (prev == top)) | ((kp + 1 < lens) & (nxt == top))
    return repeated & (top >= np.max(top))


def dr_visible(samples, lengths, sampling_ns, dr_time_ns, level, half_window_ns) -> np.ndarray:
    """(n,) bool: some sample within ``half_window_ns`` of the DR time exceeds ``level`` (DN,
    absolute: noise mean + arming level), i.e. the waveform shows the DR echo above its noise.
    False without a DR time."""
    x, lens = checks.waveforms(samples, lengths)
    n = x.shape[0]
    dt = checks.per_pulse(sampling_ns, n, "sampling_ns", positive=True)
    t = checks.per_pulse(dr_time_ns, n, "dr_time_ns", allow_nan=True)
    lv = checks.per_pulse(level, n, "level")
    if n == 0 or x.shape[1] == 0:
        return np.zeros(n, bool)
    reach = int(math.ceil(float(np.max(half_window_ns / dt)))) + 1
    centre = np.where(np.isfinite(t), np.round(np.nan_to_num(t) / dt), -10 * reach).astype(np.int64)
    k = centre[:, None] + np.arange(-reach, reach + 1)[None, :]
    inside = (k >= 0) & (k < lens[:, None]) & (np.abs(k * dt[:, None] - t[:, None]) <= half_window_ns + dt[:, None])
    v = x[np.arange(n)[:, None], np.clip(k, 0, x.shape[1] - 1)]
    return np.isfinite(t) & np.any(inside & (v > lv[:, None]), axis=1)


LIMITS = ("no_cfd_echo", "dr_below_noise", "other_echo", "same_echo_off")
"""Why a pulse with a DR echo misses the 0.10-m criterion (:func:`dr_agreement`)."""


def dr_agreement(dr_minus_cfd_m, residual_m, has_dr, visible) -> dict:
    """The paper's CFD check over all pulses with a DR echo, and what limits the rest.

    Parameters
    ----------
    dr_minus_cfd_m : (n,) DR range - own first CFD range before the correction, m (NaN: no CFD echo).
    residual_m : (n,) the same after the range correction, m.
    has_dr : (n,) bool, the pulse has a first DR echo.  visible : (n,) bool, :func:`dr_visible`.

    Returns
    -------
    dict: n_pulses (with a DR echo), within_0_10_m (share of them), n_gated (|dR| < RANGE_GATE_M),
    within_0_10_m_gated, median_residual_m (gated), mean_residual_m (gated), residual_sd_robust_m
    (gated, 1.4826 MAD), and ``limits``: per reason of :data:`LIMITS`, the count and the share of
    the pulses with a DR echo.
    """
    dr = np.asarray(dr_minus_cfd_m, dtype=np.float64)
    res = np.asarray(residual_m, dtype=np.float64)
    has = np.asarray(has_dr, dtype=bool)
    vis = np.asarray(visible, dtype=bool)
    n = int(has.sum())
    found = has & np.isfinite(dr)
    gate = found & (np.abs(dr) < RANGE_GATE_M)
    within = gate & (np.abs(res) < CFD_CHECK_M)
    r = res[gate]
    miss = has & ~within
    reasons = {
        "no_cfd_echo": has & ~np.isfinite(dr),
        "dr_below_noise": miss & found & ~gate & ~vis,
        "other_echo": miss & found & ~gate & vis,
        "same_echo_off": miss & gate,
    }
    share = (lambda m: float(m.sum() / n)) if n else (lambda m: None)
    return {
        "n_pulses": n,
        "within_0_10_m": share(within),
        "n_gated": int(gate.sum()),
        "within_0_10_m_gated": float(within.sum() / gate.sum()) if gate.any() else None,
        "median_residual_m": float(np.median(r)) if r.size else None,
        "mean_residual_m": float(np.mean(r)) if r.size else None,
        "residual_sd_robust_m": float(1.4826 * np.median(np.abs(r - np.median(r)))) if r.size else None,
        "limits": {k: {"n": int(m.sum()), "share": share(m)} for k, m in reasons.items()},
        "n_dr_below_noise": int((has & ~vis).sum()),
        "within_0_10_m_dr_above_noise": float((within & vis).sum() / (has & vis).sum()) if (has & vis).any() else None,
    }


PAPER_SHARE = 0.95
"""The paper's criterion: more than this share of pulses within 0.10 m (docs/method.md §(f))."""

BIAS_LIMIT_M = 0.02
""""No bias": |median residual| under this, m."""


def _cm(metres) -> str:
    """A length in cm to 0.1 cm, without a negative zero ("nan" for None)."""
    text = f"{100 * (np.nan if metres is None else metres):.1f}"
    return "0.0" if text == "-0.0" else text


def closing_note(agreement: dict, sampling_ns: float, arming_sd: float) -> str:
    """One paragraph: whether the paper's criterion holds, and if not what limits the rest, measured."""
    share, med, n = agreement["within_0_10_m"], agreement["median_residual_m"], agreement["n_pulses"]
    if not n or share is None:
        return "no pulse has a DR echo: the CFD cannot be checked against the sensor's ranges"
    bias = "no bias" if med is not None and abs(med) < BIAS_LIMIT_M else f"a bias of {_cm(med)} cm"
    head = (f"{100 * share:.1f} % of the {n:,} pulses with a DR echo have their first CFD echo within 0.10 m of it, "
            f"median residual {_cm(med)} cm ({bias})")
    if share >= PAPER_SHARE and bias == "no bias":
        return head + ": the paper's criterion (> 95 %, no bias) holds."
    lim = agreement["limits"]
    parts = [
        f"{100 * lim['dr_below_noise']['share']:.1f} % have a DR echo that the waveform does not show above its noise "
        f"(no sample within half a pulse width of the DR time above the arming level, {arming_sd:g} noise SDs) and "
        "the CFD fires on another echo",
        f"{100 * lim['no_cfd_echo']['share']:.1f} % have no CFD echo at all",
        f"{100 * lim['other_echo']['share']:.1f} % a CFD echo on another return although the DR echo shows (|dR| >= 1 m)",
        f"{100 * lim['same_echo_off']['share']:.1f} % the same echo but 0.10-1 m off (residual robust SD "
        f"{_cm(agreement['residual_sd_robust_m'])} cm at {sampling_ns:g}-ns sampling)",
    ]
    vis = agreement.get("within_0_10_m_dr_above_noise")
    tail = (f"; among pulses whose DR echo shows above the noise the share is {100 * vis:.1f} %" if vis is not None else "")
    return head + ", short of the paper's > 95 %. Of all pulses with a DR echo, " + "; ".join(parts) + tail + "."


def dr_minus_cfd(dr_time_ns, cfd_time_ns) -> np.ndarray:
    """DR range - CFD range, m, from the two times (ns from the first sample)."""
    return (np.asarray(dr_time_ns, dtype=np.float64) - np.asarray(cfd_time_ns, dtype=np.float64)) * RANGE_PER_NS
