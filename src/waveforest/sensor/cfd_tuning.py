"""Tuning of the CFD fraction and delay against the sensor's DR ranges (docs/method.md §(f)).

The paper tuned its CFD "by running it on real WFs (planar surfaces, mature forest, birch
saplings) and comparing with the real DR ranges: |dR| < 0.10 m for > 95 % of pulses, no bias".

Planar echoes alone cannot tell the pairs (f, delay) apart. For a Gaussian echo of SD s the CFD
time is ``mu + delay/2 + s^2 ln(f)/delay`` (cfd.py): on echoes of one width a wrong pair only
shifts every range by one constant, which the amplitude-dependent range correction absorbs.
Echoes wider than the system pulse (vegetation) show a wrong pair as a bias that grows with
the echo width, s^2 (ln f / delay - ln f_DR / delay_DR). The criterion is therefore the
paper's "no bias", asked of every class of echo width rather than of all pulses at once:

1. run the CFD with (f, delay) on the tuning pulses (planar targets and a seeded random subset
   of the dataset's pulses, whose echoes span ground, low vegetation and crowns);
2. fit the range correction dR(Apeak) on them (:func:`fit_range_correction`);
3. split the residuals by the first echo's FWHM (at the DR time) relative to the system pulse
   FWHM at :data:`WIDTH_EDGES`: system-like, wider, much wider;
4. score = the largest |median residual| over the classes, m.

The grid pair with the smallest score wins. How well tuning recovers the virtual campaign's
DR discriminator: docs/validation.md ("Tuning recovers the DR discriminator").
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pandas as pd

from waveforest.constants import RANGE_PER_NS
from waveforest.sensor.cfd import RangeCorrection, detect_echoes, fit_range_correction
from waveforest.sensor.params import CFD_CHECK_M, RANGE_GATE_M, CFDParams

FRACTIONS = np.round(np.arange(0.20, 0.601, 0.05), 2)
"""CFD fractions f of the tuning grid."""

DELAYS_FWHM = np.round(np.arange(0.30, 0.801, 0.05), 2)
"""CFD delays of the tuning grid, in system pulse FWHMs."""

WIDTH_EDGES = (1.1, 1.3)
"""Edges of the echo-width classes, in system pulse FWHMs (first-echo FWHM at the DR time)."""

MIN_CLASS_PULSES = 50
"""Fewest gated pulses per width class; with fewer in any class the CFD is not tuned."""


def width_class(width_ns, system_fwhm_ns: float) -> np.ndarray:
    """Echo-width class of each pulse: 0 system-like, 1 wider, 2 much wider (:data:`WIDTH_EDGES`); -1 NaN."""
    w = np.asarray(width_ns, dtype=np.float64) / float(system_fwhm_ns)
    cls = np.searchsorted(np.asarray(WIDTH_EDGES), w, side="right").astype(np.int64)
    return np.where(np.isfinite(w), cls, -1)


@dataclass(frozen=True)
class CFDRanges:
    """One CFD run on pulses with DR echoes: residuals after the range correction fitted on them."""

    cfd: CFDParams
    dr_minus_cfd_m: np.ndarray
    amplitude: np.ndarray
    correction: RangeCorrection
    residual_m: np.ndarray
    gate: np.ndarray

    def class_bias(self, classes: np.ndarray) -> np.ndarray:
        """Median residual per width class 0..len(WIDTH_EDGES), m (NaN below MIN_CLASS_PULSES)."""
        out = np.full(len(WIDTH_EDGES) + 1, np.nan)
        for k in range(out.size):
            r = self.residual_m[self.gate & (classes == k)]
            if r.size >= MIN_CLASS_PULSES:
                out[k] = np.median(r)
        return out


def cfd_ranges(samples, lengths, sampling_ns, dr_time_ns, noise_mean, noise_sd, cfd: CFDParams, *,
               n_bins: int = 8, min_per_bin: int = 20) -> CFDRanges:
    """Own first CFD echo against the first DR echo, range correction fitted on the gated pulses.

    dR = (DR time - CFD time) x c/2, m; gate |dR| < RANGE_GATE_M (different echoes otherwise).
    """
    ech = detect_echoes(samples, lengths, sampling_ns, noise_mean, noise_sd, cfd, 1)
    dr = (np.asarray(dr_time_ns, dtype=np.float64) - ech.times_ns[:, 0]) * RANGE_PER_NS
    amp = ech.amplitudes[:, 0]
    gate = np.isfinite(dr) & np.isfinite(amp) & (np.abs(dr) < RANGE_GATE_M)
    corr = fit_range_correction(amp[gate], dr[gate], n_bins=n_bins, min_per_bin=min_per_bin)
    return CFDRanges(cfd, dr, amp, corr, dr - corr(amp), gate)


@dataclass(frozen=True)
class CFDTuning:
    """The tuned CFD, its run on the tuning pulses, and the grid of scores.

    ``classes``: width class of each pulse (:func:`width_class`). ``grid`` columns: fraction,
    delay_ns, score_m, bias_m_w0.. (per width class), frac_within_0_10_m. ``tuned`` is False
    (and ``cfd`` the starting pair) when not asked for or a width class has too few pulses.
    """

    ranges: CFDRanges
    classes: np.ndarray
    grid: pd.DataFrame
    tuned: bool
    reason: str

    @property
    def cfd(self) -> CFDParams:
        """The chosen CFD (that of ``ranges``)."""
        return self.ranges.cfd


def tune_cfd(samples, lengths, sampling_ns, dr_time_ns, width_ns, noise_mean, noise_sd, start: CFDParams,
             system_fwhm_ns: float, *, tune: bool = True, n_bins: int = 8, min_per_bin: int = 20) -> CFDTuning:
    """Grid search of (f, delay) for no bias in any echo-width class (module docstring).

    Parameters
    ----------
    samples : (n, n_s) DN, AGC-normalised.  lengths : (n,).  sampling_ns : (n,) ns.
    dr_time_ns : (n,) first DR echo, ns from the first sample.  width_ns : (n,) FWHM of the
        first echo at the DR time, ns.  noise_mean, noise_sd : DN, scalars or (n,); the CFD arms
        at ``arming_sd`` x noise_sd (the recorded noise: SD / AGC gain in normalised DN).
    start : the configured CFD (arming, dead time; its pair is kept if tuning is not possible).
    system_fwhm_ns : FWHM of S(t), ns.  tune : False = keep the start pair (its ranges only).
    n_bins, min_per_bin : range-correction fit.
    """
    classes = width_class(width_ns, system_fwhm_ns)
    counts = np.bincount(classes[classes >= 0], minlength=len(WIDTH_EDGES) + 1)
    base = replace(start, dead_time_ns=start.dead_time_ns if start.dead_time_ns is not None else system_fwhm_ns)
    run = lambda c: cfd_ranges(samples, lengths, sampling_ns, dr_time_ns, noise_mean, noise_sd, c,  # noqa: E731
                               n_bins=n_bins, min_per_bin=min_per_bin)
    if not tune or counts.min() < MIN_CLASS_PULSES:
        c = base.resolved(system_fwhm_ns)
        why = ("not asked for" if not tune else f"echoes per width class {counts.tolist()} (edges {WIDTH_EDGES} "
               f"x FWHM); tuning needs >= {MIN_CLASS_PULSES} in each")
        return CFDTuning(run(c), classes, pd.DataFrame(), False, why)
    rows, best = [], None
    for f in FRACTIONS:
        for d in DELAYS_FWHM:
            c = replace(base, fraction=float(f), delay_ns=float(d) * system_fwhm_ns).resolved(system_fwhm_ns)
            rr = run(c)
            bias = rr.class_bias(classes)
            score = float(np.nanmax(np.abs(bias))) if np.isfinite(bias).any() else np.inf
            within = float(np.mean(np.abs(rr.residual_m[rr.gate]) < CFD_CHECK_M)) if rr.gate.any() else np.nan
            rows.append({"fraction": float(f), "delay_ns": c.delay_ns, "score_m": score,
                         **{f"bias_m_w{k}": float(b) for k, b in enumerate(bias)}, "frac_within_0_10_m": within})
            if best is None or score < best[0]:
                best = (score, rr)
    return CFDTuning(best[1], classes, pd.DataFrame(rows), True,
                     f"smallest largest |median residual| over echo-width classes: {best[0]:.4f} m")
