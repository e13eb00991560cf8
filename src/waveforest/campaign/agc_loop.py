"""The ALS60's automatic gain control (AGC) as the virtual sensor really runs it.

Eq. 1 of docs/method.md §(b) is the *gain law*: a pulse recorded with AGC value ``AGC`` has its
signal (not its noise) multiplied by

    gain = 1 + (AGC - a_law) * b_law                                          (Eq. 1)

with a dataset-specific true ``b_law``. The AGC value itself comes from a feedback loop
that reacts to the signal level of the previous pulses:

* the terrain between the simulated sites (forest, clear-cuts, fields: most of every scan
  line) drives the loop towards a level g_bg(t) = ``bg_mean`` + X(t), X an
  Ornstein-Uhlenbeck process of SD ``bg_sd`` and correlation time ``bg_tau_s``;
* between two pulses dt apart the loop state g relaxes towards g_bg with time constant
  ``loop_tau_s``: g <- g_bg + (g - g_bg) exp(-dt / loop_tau_s);
* each pulse's observed (gained, possibly saturated) peak amplitude A pushes the loop:
  g <- g - ``loop_gain`` * ln(max(A, floor) / ``setpoint_dn``) (strong echoes lower the gain);
* the recorded AGC is the integer round(g + jitter), jitter ~ N(0, ``jitter_sd``), clipped
  to the 8-bit range and to where the gain law stays >= ``MIN_GAIN``; the gain actually
  applied is that of the recorded integer, so Eq. 1 with the true b undoes it exactly.

Each strip starts with g at its terrain level. The loop runs in time order within a strip:
a sequential Numba kernel (the state carries from pulse to pulse).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

MIN_GAIN = 0.2
"""Lowest gain the loop may reach (AGC values below are never used)."""

AMP_FLOOR_DN = 1.0
"""Observed amplitudes below this (DN) push the loop as if they were this large."""

AGC_MAX = 255
"""8-bit AGC register."""


@dataclass(frozen=True)
class AGCParams:
    """True AGC behaviour of one dataset (``sensor_truth.csv`` columns ``agc_*``)."""

    law_a: float
    law_b: float
    bg_mean: float
    bg_sd: float
    bg_tau_s: float
    loop_tau_s: float
    loop_gain: float
    setpoint_dn: float
    jitter_sd: float

    @classmethod
    def from_row(cls, row) -> AGCParams:
        """From a row of :func:`waveforest.campaign.params.load_datasets`."""
        return cls(*(float(row[f"agc_{k}"]) for k in (
            "law_a", "law_b", "bg_mean", "bg_sd", "bg_tau_s", "loop_tau_s", "loop_gain",
            "setpoint_dn", "jitter_sd")))

    def gain(self, agc) -> np.ndarray:
        """Gain of the true law (Eq. 1) for AGC values ``agc``."""
        return 1.0 + (np.asarray(agc, dtype=np.float64) - self.law_a) * self.law_b

    def b_at(self, a: float) -> float:
        """The b of Eq. 1 that describes the same law with reference AGC ``a``.

        1 + (AGC - a_law) b_law = c (1 + (AGC - a) b_law / c) with c = 1 + (a - a_law) b_law,
        so an analysis that sets a = (say) the dataset mean AGC should find b_law / c, and its
        normalised signal is c times the unit-gain signal (see :meth:`scale_at`).
        """
        return self.law_b / self.scale_at(a)

    def scale_at(self, a: float) -> float:
        """Gain of the true law at AGC = ``a`` (the factor c above)."""
        return float(1.0 + (a - self.law_a) * self.law_b)

    def agc_bounds(self) -> tuple[int, int]:
        """Smallest and largest AGC the loop may record."""
        lo = int(np.ceil(self.law_a - (1.0 - MIN_GAIN) / self.law_b)) if self.law_b > 0 else 0
        return max(0, lo), AGC_MAX


@njit(cache=True, nogil=True)
def _agc_loop_kernel(t_s, a0_dn, strip, z_bg, z_jit, law_a, law_b, bg_mean, bg_sd, bg_tau,
                     loop_tau, loop_gain, setpoint, jitter_sd, saturation, agc_lo, agc_hi,
                     agc_out, gain_out, obs_out):
    n = t_s.shape[0]
    x = 0.0
    g = 0.0
    for i in range(n):
        if i == 0 or strip[i] != strip[i - 1]:
            x = bg_sd * z_bg[i]
            g = bg_mean + x
        else:
            dt = t_s[i] - t_s[i - 1]
            r = np.exp(-dt / bg_tau)
            x = x * r + bg_sd * np.sqrt(1.0 - r * r) * z_bg[i]
            gbg = bg_mean + x
            g = gbg + (g - gbg) * np.exp(-dt / loop_tau)
        v = np.rint(g + jitter_sd * z_jit[i])
        if v < agc_lo:
            v = agc_lo
        if v > agc_hi:
            v = agc_hi
        gain = 1.0 + (v - law_a) * law_b
        a = gain * a0_dn[i]
        if saturation > 0.0:
            a = saturation * np.tanh(a / saturation)
        agc_out[i] = v
        gain_out[i] = gain
        obs_out[i] = a
        g = g - loop_gain * np.log(max(a, AMP_FLOOR_DN) / setpoint)


def agc_sequence(t_s, a0_dn, strip, params: AGCParams, rng: np.random.Generator,
                 saturation_dn: float = 0.0):
    """Run the AGC loop over the pulses of a dataset in time order.

    Parameters
    ----------
    t_s : (n,) float64, s
        GPS times, non-decreasing within each strip; the pulses of a strip are contiguous.
    a0_dn : (n,) float64, DN
        Peak amplitude of each pulse's noise-free analog signal at unit gain.
    strip : (n,) int64
        Strip index of each pulse.
    params : AGCParams
    rng : numpy.random.Generator
        Draws 2n standard normals (terrain process, jitter), always the same number.
    saturation_dn : float
        Detector saturation level L (the ``nonlinearity`` effect): the loop sees
        L tanh(gain a0 / L); 0 = linear.

    Returns
    -------
    agc : (n,) uint8
    gain : (n,) float64
        1 + (agc - a_law) b_law.
    observed_dn : (n,) float64
        Peak amplitude the loop saw (gained, saturated), DN.
    """
    t_s = np.require(t_s, np.float64, ["C", "W"])  # writable: Numba compiles read-only arrays as another type
    a0 = np.require(a0_dn, np.float64, ["C", "W"])
    strip = np.require(strip, np.int64, ["C", "W"])
    n = t_s.shape[0]
    if t_s.ndim != 1 or a0.shape != (n,) or strip.shape != (n,):
        raise ValueError("t_s, a0_dn, strip: expected 1-D arrays of one length")
    if not (np.all(np.isfinite(t_s)) and np.all(np.isfinite(a0))) or np.any(a0 < 0):
        raise ValueError("t_s, a0_dn: expected finite values, a0_dn >= 0")
    same = strip[1:] == strip[:-1]
    if np.any(np.diff(t_s)[same] < 0):
        raise ValueError("t_s: expected non-decreasing times within a strip")
    if len(np.unique(strip)) != 1 + int(np.count_nonzero(~same)):
        raise ValueError("strip: the pulses of a strip must be contiguous")
    if params.bg_tau_s <= 0 or params.loop_tau_s <= 0 or params.setpoint_dn <= 0:
        raise ValueError("AGCParams: bg_tau_s, loop_tau_s and setpoint_dn must be > 0")
    z = rng.standard_normal((2, n))
    lo, hi = params.agc_bounds()
    agc = np.empty(n)
    gain = np.empty(n)
    obs = np.empty(n)
    if n:
        _agc_loop_kernel(t_s, a0, strip, z[0], z[1], params.law_a, params.law_b, params.bg_mean,
                         params.bg_sd, params.bg_tau_s, params.loop_tau_s, params.loop_gain,
                         params.setpoint_dn, params.jitter_sd, float(saturation_dn), float(lo),
                         float(hi), agc, gain, obs)
    return agc.astype(np.uint8), gain, obs
