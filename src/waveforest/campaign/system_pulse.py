"""The true system waveform S(t) of the virtual ALS60: asymmetric, with a tail.

The analysis model calibrates S(t) from targets (Eq. 8) and may assume a Gaussian; the
virtual sensor's real S(t) is not Gaussian. Its shape is an exponentially modified Gaussian
(a Gaussian rise of SD ``sigma`` convolved with an exponential tail of time constant
``tau``, the usual form of a laser pulse seen through an avalanche-photodiode receiver),
plus a weak after-pulse (receiver ringing) ``afterpulse_rel`` times the peak, a Gaussian of
the same ``sigma`` ``afterpulse_delay_fwhm`` FWHMs after the main peak:

    shape(t) = EMG(t; sigma, tau) + afterpulse_rel * max(EMG) * exp(-(t - t_peak - d)^2 / (2 sigma^2))

``sigma`` is solved so that the FWHM of the shape equals the dataset's pulse width
(Table 2). The scale makes S(t) a system waveform in the units of Eq. 7 (DN m^2 per unit
sigma, sigma per unit emitted power): its peak ``peak_dn_m2`` is the amplitude that a spike
target of unit sigma gives at 1 m. The time axis is the BIN_NS grid with t = 0 at the time
that the sensor's own DR discriminator (:mod:`.dr_cfd`) reports for a spike target, so that
a planar target's DR range is unbiased (before the range walk).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from waveforest.campaign.dr_cfd import dr_cfd
from waveforest.constants import BIN_NS

SHAPE_CUTOFF = 1e-5
"""The tabulated S(t) extends until the shape falls below this fraction of its peak."""

FINE_NS = 0.001
"""Grid step used to measure the FWHM of the analytic shape, ns."""


def emg(t, sigma: float, tau: float) -> np.ndarray:
    """Exponentially modified Gaussian density (mean of the Gaussian at 0).

    Parameters
    ----------
    t : array, ns
    sigma : float, ns
        SD of the Gaussian rise.
    tau : float, ns
        Time constant of the exponential tail (tau -> 0 gives the Gaussian).

    Returns
    -------
    array, 1/ns
        The density; it integrates to 1.
    """
    from scipy.special import erfc, erfcx

    t = np.asarray(t, dtype=np.float64)
    z = (sigma / tau - t / sigma) / np.sqrt(2.0)
    with np.errstate(over="ignore", under="ignore"):
        # exp(a) erfc(z) with a = z^2 - t^2 / (2 sigma^2); erfcx keeps it finite for z > 0
        pos = np.exp(-t * t / (2 * sigma * sigma)) * erfcx(np.maximum(z, 0.0))
        neg = np.exp(sigma * sigma / (2 * tau * tau) - t / tau) * erfc(np.minimum(z, 0.0))
    return np.where(z > 0, pos, neg) / (2.0 * tau)


def fwhm(t: np.ndarray, y: np.ndarray) -> float:
    """Full width at half maximum of a sampled single-peaked curve, ns (linear interpolation).

    The width spans from the first rise above half of the maximum to the last fall below it
    on either side of the maximum.
    """
    t = np.asarray(t, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    k = int(np.argmax(y))
    half = 0.5 * y[k]
    left = k
    while left > 0 and y[left - 1] >= half:
        left -= 1
    right = k
    while right < len(y) - 1 and y[right + 1] >= half:
        right += 1
    if left == 0 or right == len(y) - 1:
        raise ValueError("fwhm: the curve does not fall below half maximum on both sides")
    tl = t[left - 1] + (half - y[left - 1]) / (y[left] - y[left - 1]) * (t[left] - t[left - 1])
    tr = t[right] + (y[right] - half) / (y[right] - y[right + 1]) * (t[right + 1] - t[right])
    return float(tr - tl)


def _shape(t, sigma, tau, afterpulse_rel, afterpulse_delay_ns):
    main = emg(t, sigma, tau)
    tt = np.arange(-6 * sigma, 6 * sigma + 12 * tau, FINE_NS * sigma)
    ref = emg(tt, sigma, tau)
    k = int(np.argmax(ref))
    t_peak, peak = tt[k], ref[k]
    after = afterpulse_rel * peak * np.exp(-((t - t_peak - afterpulse_delay_ns) ** 2) / (2 * sigma * sigma))
    return (main + after) / peak, t_peak


def _fwhm_ratio(tail_ratio: float) -> float:
    """FWHM of the EMG with sigma = 1 and tau = tail_ratio (no after-pulse), in units of sigma."""
    tt = np.arange(-8.0, 8.0 + 20.0 * tail_ratio, FINE_NS)
    return fwhm(tt, emg(tt, 1.0, tail_ratio))


@dataclass(frozen=True)
class TrueSystemWaveform:
    """The true S(t) of a dataset.

    Attributes
    ----------
    t_ns : (m,) float64, ns
        BIN_NS grid, t = 0 at the sensor's DR (CFD) time of a spike target.
    s : (m,) float64, DN m^2 per unit sigma
        S(t) at unit gain (AGC = the gain law's reference a).
    fwhm_ns, sigma_ns, tau_ns : float
        FWHM of S(t) and the parameters of its shape.
    cfd_offset_ns : float
        DR time that the discrete discriminator finds for a spike at t = 0 (~0 by
        construction; subtracted when the sensor converts crossings to ranges).
    """

    t_ns: np.ndarray
    s: np.ndarray
    fwhm_ns: float
    sigma_ns: float
    tau_ns: float
    cfd_offset_ns: float

    @property
    def i0(self) -> int:
        """Index of t = 0 in :attr:`t_ns`."""
        return int(round(-self.t_ns[0] / BIN_NS))

    @property
    def peak(self) -> float:
        """Peak of S(t), DN m^2 per unit sigma."""
        return float(self.s.max())


def true_system_waveform(fwhm_ns: float, tail_ratio: float, afterpulse_rel: float,
                         afterpulse_delay_fwhm: float, peak_dn_m2: float, *,
                         cfd_fraction: float, cfd_delay_fwhm: float) -> TrueSystemWaveform:
    """Tabulate the true system waveform of a dataset (see the module docstring).

    Parameters
    ----------
    fwhm_ns : float, ns
        Required FWHM (Table 2 ``pulse_width_fwhm_ns``).
    tail_ratio : float
        tau / sigma of the exponentially modified Gaussian (> 0).
    afterpulse_rel, afterpulse_delay_fwhm : float
        After-pulse amplitude (fraction of the peak, < 0.5) and delay (FWHMs).
    peak_dn_m2 : float, DN m^2 per unit sigma
        Peak of S(t).
    cfd_fraction, cfd_delay_fwhm : float
        The sensor's DR discriminator (fraction, delay in FWHMs), which fixes t = 0.
    """
    if fwhm_ns <= 0 or tail_ratio <= 0 or peak_dn_m2 <= 0:
        raise ValueError("fwhm_ns, tail_ratio and peak_dn_m2 must be > 0")
    if not 0 <= afterpulse_rel < 0.5:
        raise ValueError("afterpulse_rel: expected 0 <= value < 0.5 (below half maximum)")
    sigma = fwhm_ns / _fwhm_ratio(tail_ratio)
    tau = tail_ratio * sigma
    delay_after = afterpulse_delay_fwhm * fwhm_ns

    def shape(t):
        return _shape(t, sigma, tau, afterpulse_rel, delay_after)[0]

    _, t_peak = _shape(np.zeros(1), sigma, tau, afterpulse_rel, delay_after)
    # analytic CFD time of the sensor's discriminator on the noise-free shape
    delta = cfd_delay_fwhm * fwhm_ns

    def y(t):
        return shape(np.array([t - delta]))[0] - cfd_fraction * shape(np.array([t]))[0]

    t_left = t_peak - 4.0 * sigma
    from scipy.optimize import brentq

    t_cfd = brentq(y, t_left, t_peak + delta, xtol=1e-9)
    # tabulate on the BIN_NS grid with t = 0 at t_cfd
    lo = t_peak - 8.0 * sigma - t_cfd
    hi = t_peak + delay_after + 6.0 * sigma + tau * np.log(1.0 / SHAPE_CUTOFF) - t_cfd
    k = np.arange(int(np.floor(lo / BIN_NS)), int(np.ceil(hi / BIN_NS)) + 1)
    t = k * BIN_NS
    s = shape(t + t_cfd)
    s = s / s.max() * peak_dn_m2
    keep = np.flatnonzero(s >= SHAPE_CUTOFF * peak_dn_m2)
    k0, k1 = keep[0], keep[-1]
    k0 = min(k0, int(np.flatnonzero(t == 0.0)[0]) if np.any(t == 0.0) else k0)
    t, s = t[k0:k1 + 1], s[k0:k1 + 1]
    # the discrete discriminator's time for a spike at t = 0
    pos, _, cnt = dr_cfd(s[None, :] / s.max() * 100.0, fraction=cfd_fraction, delay_ns=delta,
                         arm_dn=1.0, dead_time_ns=fwhm_ns, fwhm_ns=fwhm_ns)
    if cnt[0] < 1:
        raise ValueError("true_system_waveform: the discriminator finds no echo in S(t)")
    offset = t[0] + pos[0, 0] * BIN_NS
    return TrueSystemWaveform(t_ns=t.copy(), s=s.copy(), fwhm_ns=fwhm(t, s), sigma_ns=float(sigma),
                              tau_ns=float(tau), cfd_offset_ns=float(offset))
