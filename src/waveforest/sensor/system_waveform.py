"""The system waveform S(t) of Eqs. 6-8 (docs/method.md §(c), e).

S(t) is tabulated on the 0.05-ns grid of sigma(t). Units: DN m^2 per unit sigma, where sigma
is the per-bin sum of the MCRT cross-section per unit emitted power (a Lambertian plane at
normal incidence gives rho / pi), so that a planar target at range R produces
``V(t) = S(t - tau) * sigma / R^2`` above the noise mean (Eq. 7, with Eq. 8 its inverse).

Time origin: t = 0 is the CFD echo time of a planar target (a spike in sigma), so that the
CFD of :mod:`waveforest.sensor.cfd` on a simulated planar return finds the spike's time and
simulated ranges reproduce the DR ranges without bias. A calibrated S(t) gets this origin from
the alignment on the DR echo times (docs/method.md §(e)); the analytic Gaussian is placed so that the
CFD crossing is at 0 (for the default CFD: the Gaussian peak).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from waveforest.errors import WaveforestError
from waveforest.io.results import read_system_waveform_table, write_system_waveform_table
from waveforest.sensor.cfd import cfd_row
from waveforest.sensor.params import CFD_SELF_ARM_FRACTION, FINE_NS, GAUSSIAN_EXTENT_SD, GRID_TOL_NS, CFDParams

_FWHM_PER_SD = 2.0 * math.sqrt(2.0 * math.log(2.0))
"""FWHM of a Gaussian in units of its SD (2.3548)."""


def half_max_width(t: np.ndarray, s: np.ndarray) -> float:
    """Full width at half maximum of the main lobe of s(t), linear interpolation, ns.

    From the global maximum outward to the first samples at or below half of it; NaN if the
    lobe reaches either end of the table or the maximum is not positive.
    """
    s = np.asarray(s, dtype=np.float64)
    if s.size < 3:
        return float("nan")
    kp = int(np.argmax(s))
    peak = s[kp]
    if not peak > 0:
        return float("nan")
    half = 0.5 * peak
    below = np.flatnonzero(s[:kp] <= half)
    above = np.flatnonzero(s[kp:] <= half)
    if below.size == 0 or above.size == 0:
        return float("nan")
    kl = below[-1]
    kr = kp + above[0]
    tl = t[kl] + (half - s[kl]) / (s[kl + 1] - s[kl]) * (t[kl + 1] - t[kl])
    tr = t[kr - 1] + (half - s[kr - 1]) / (s[kr] - s[kr - 1]) * (t[kr] - t[kr - 1])
    return float(tr - tl)


@dataclass
class SystemWaveform:
    """S(t) on the 0.05-ns grid (Eq. 7).

    Parameters
    ----------
    t_ns : (k,) float64, ns; evenly spaced by :data:`FINE_NS`; t = 0 is the CFD time of a
        planar target.
    s : (k,) float64, DN m^2 per unit sigma.
    s_sd : (k,) float64 or None, spread (SD over calibration pulses) of s; NaN where unknown.
    meta : dict, free-form provenance (dataset, n_pulses, ...), kept by save/load.
    """

    t_ns: np.ndarray
    s: np.ndarray
    s_sd: np.ndarray | None = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        t = np.ascontiguousarray(self.t_ns, dtype=np.float64)
        s = np.ascontiguousarray(self.s, dtype=np.float64)
        if t.ndim != 1 or s.shape != t.shape:
            raise ValueError(f"SystemWaveform: t_ns and s must be 1-D of equal length, got {t.shape}, {s.shape}")
        if t.size < 2:
            raise ValueError("SystemWaveform: needs at least 2 samples")
        if not (np.isfinite(t).all() and np.isfinite(s).all()):
            raise ValueError("SystemWaveform: t_ns and s must be finite")
        step = np.diff(t)
        if np.abs(step - FINE_NS).max() > GRID_TOL_NS:
            raise ValueError(f"SystemWaveform: t_ns must be spaced by {FINE_NS} ns (the sigma grid)")
        self.t_ns, self.s = t, s
        if self.s_sd is not None:
            sd = np.ascontiguousarray(self.s_sd, dtype=np.float64)
            if sd.shape != t.shape:
                raise ValueError("SystemWaveform: s_sd must have the shape of s")
            self.s_sd = sd

    # -- properties ---------------------------------------------------------------------
    @property
    def fwhm_ns(self) -> float:
        """FWHM of the main lobe, ns (linear interpolation of the half-maximum crossings)."""
        return half_max_width(self.t_ns, self.s)

    @property
    def energy(self) -> float:
        """Integral of S(t), DN m^2 ns per unit sigma: sum(s) * 0.05 ns."""
        return float(self.s.sum() * FINE_NS)

    @property
    def peak(self) -> float:
        """Largest value of S(t), DN m^2 per unit sigma."""
        return float(self.s.max())

    @property
    def t_peak_ns(self) -> float:
        """Time of the largest value, ns."""
        return float(self.t_ns[int(np.argmax(self.s))])

    # -- transformations ----------------------------------------------------------------
    def stretched(self, fwhm_ns: float) -> SystemWaveform:
        """The same pulse shape with FWHM ``fwhm_ns`` at constant energy (docs/method.md §(i3)).

        ``s'(t) = s(t / k) / k`` with ``k = fwhm_ns / self.fwhm_ns``; t = 0 stays at 0 (for a
        CFD whose delay scales with the pulse width, the default, the CFD time stays at 0).
        """
        w0 = self.fwhm_ns
        if not (np.isfinite(fwhm_ns) and fwhm_ns > 0):
            raise ValueError(f"stretched: fwhm_ns must be > 0, got {fwhm_ns}")
        if not np.isfinite(w0):
            raise ValueError("stretched: the FWHM of this S(t) is undefined")
        k = fwhm_ns / w0
        n = int(math.floor((self.t_ns[-1] - self.t_ns[0]) * k / FINE_NS + 1e-9)) + 1
        t_new = self.t_ns[0] * k + FINE_NS * np.arange(max(n, 2))
        s_new = np.interp(t_new / k, self.t_ns, self.s, left=0.0, right=0.0) / k
        sd_new = None
        if self.s_sd is not None:
            sd_new = np.interp(t_new / k, self.t_ns, self.s_sd, left=np.nan, right=np.nan) / k
        return SystemWaveform(t_new, s_new, sd_new, dict(self.meta, stretched_from_fwhm_ns=w0))

    def scaled(self, factor: float) -> SystemWaveform:
        """S(t) times ``factor`` (e.g. a different peak power)."""
        sd = None if self.s_sd is None else self.s_sd * abs(factor)
        return SystemWaveform(self.t_ns.copy(), self.s * factor, sd, dict(self.meta))

    def shifted(self, dt_ns: float) -> SystemWaveform:
        """The same table with its time axis moved by ``dt_ns`` (S'(t) = S(t - dt))."""
        sd = None if self.s_sd is None else self.s_sd.copy()
        return SystemWaveform(self.t_ns + dt_ns, self.s.copy(), sd, dict(self.meta))

    def cfd_time_ns(self, cfd: CFDParams | None = None) -> float:
        """CFD time of this pulse as a spike response, ns on the t_ns axis.

        The arming level is :data:`CFD_SELF_ARM_FRACTION` of the peak (no noise here). For a
        correctly aligned S(t) this is 0 to within a fine step.
        """

        cfd = (cfd or CFDParams()).resolved(self.fwhm_ns)
        t = np.full(1, np.nan)
        a = np.full(1, np.nan)
        row = self.s.astype(np.float64)
        n = cfd_row(row, row.size, FINE_NS, 0.0, CFD_SELF_ARM_FRACTION * self.peak,
                     float(cfd.fraction), cfd.fine_delay(), cfd.fine_dead(), 1, t, a)
        if n == 0:
            raise ValueError("cfd_time_ns: the CFD finds no echo in S(t)")
        return float(self.t_ns[0] + t[0])

    def aligned_to_cfd(self, cfd: CFDParams | None = None) -> SystemWaveform:
        """The table shifted so that its CFD time is 0 (the convention of this class)."""
        return self.shifted(-self.cfd_time_ns(cfd))

    # -- persistence --------------------------------------------------------------------
    def save(self, path: str | Path) -> Path:
        """Write Parquet with columns t_ns, s, s_sd (NaN where unknown), atomically."""
        sd = self.s_sd if self.s_sd is not None else np.full_like(self.s, np.nan)
        return write_system_waveform_table(self.t_ns, self.s, sd, self.meta, path)

    def to_dict(self) -> dict:
        """JSON-ready arrays (t_ns, s) and FWHM/energy."""
        return {"t_ns": self.t_ns.tolist(), "s": self.s.tolist(), "fwhm_ns": self.fwhm_ns, "energy": self.energy}


def load_system_waveform(path: str | Path) -> SystemWaveform:
    """Read a system waveform written by :meth:`SystemWaveform.save`."""
    t, s, sd, meta = read_system_waveform_table(path)
    try:
        return SystemWaveform(t, s, sd, meta)
    except ValueError as exc:
        raise WaveforestError(f"{path}: {exc}") from None


def gaussian_system_waveform(fwhm_ns: float, peak: float, *, cfd: CFDParams | None = None) -> SystemWaveform:
    """An analytic Gaussian S(t) of the given FWHM (ns) and peak (DN m^2 per unit sigma).

    Placed so that the CFD time is t = 0: the centre is at ``-(delay/2 + sd^2 ln f / delay)``
    (0 for the default CFD, whose crossing is the peak of a system-width pulse). Tabulated
    over +-:data:`GAUSSIAN_EXTENT_SD` SDs around the centre on the 0.05-ns grid (t = i * 0.05).
    """
    if not (np.isfinite(fwhm_ns) and fwhm_ns > 0):
        raise ValueError(f"gaussian_system_waveform: fwhm_ns must be > 0, got {fwhm_ns}")
    if not (np.isfinite(peak) and peak > 0):
        raise ValueError(f"gaussian_system_waveform: peak must be > 0, got {peak}")
    sd = fwhm_ns / _FWHM_PER_SD
    cfd = (cfd or CFDParams()).resolved(fwhm_ns)
    d = cfd.fine_delay() * FINE_NS
    centre = -(d / 2.0 + sd**2 * math.log(cfd.fraction) / d)
    i0 = int(math.floor((centre - GAUSSIAN_EXTENT_SD * sd) / FINE_NS))
    i1 = int(math.ceil((centre + GAUSSIAN_EXTENT_SD * sd) / FINE_NS))
    t = FINE_NS * np.arange(i0, i1 + 1)
    s = peak * np.exp(-0.5 * ((t - centre) / sd) ** 2)
    return SystemWaveform(t, s, None, {"kind": "gaussian", "fwhm_ns": float(fwhm_ns), "peak": float(peak)})
