"""Parameters and named tolerances of the sensor model and the waveform processing.

Every threshold, epsilon and default of ``waveforest.sensor`` that is not a config key lives
here (STYLE.md: tolerances as named constants in one module), next to the two parameter
records that the config fills: :class:`CFDParams` (docs/method.md §(f)) and :class:`FeatureParams`
(docs/method.md §(h)).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from waveforest.constants import BIN_NS

FINE_NS = BIN_NS
"""Fine time grid of the processing, ns: S(t), sigma(t), the CFD upsampling and the
calibration resampling all use it (docs/method.md §(c), e, f)."""

GRID_TOL_NS = 1e-6
"""Largest deviation of a tabulated S(t) time step from :data:`FINE_NS`, ns."""

FINE_EPS = 1e-9
"""Slack when counting fine-grid points that fit into a record (floating-point safety)."""

CFD_SELF_ARM_FRACTION = 0.05
"""Arming threshold, as a fraction of the peak, used when the CFD is run on a noise-free
system waveform itself (:meth:`SystemWaveform.cfd_time_ns`): the threshold only has to arm
the CFD before the crossing, and a few per cent keeps it above the noise of a calibrated S(t)."""

CFD_PERSIST_FRACTION = 0.5
"""A + to - crossing of the CFD signal counts only if the signal stays <= 0 for this fraction
of the delay after it; shorter dips are noise on a leading edge (they otherwise trigger early
on strong echoes whose far tail arms the CFD)."""

GAUSSIAN_EXTENT_SD = 6.0
"""Half-length of an analytic Gaussian S(t), in standard deviations (exp(-18) ~ 1.5e-8)."""

ECHO_SEARCH_NS = 2.0
"""Default largest distance, ns, between an echo time and the nearest sample above the
segment threshold (the segment must contain the echo; docs/method.md §(h))."""

GAIN_MIN = 0.05
"""Smallest AGC gain 1 + (AGC - a) b allowed in Eq. 1; the b search interval is narrowed so
that every pulse of a dataset keeps at least this gain (a gain <= 0 has no meaning)."""

QUANTISATION_VAR = 1.0 / 12.0
"""Variance of rounding to integer DN, DN^2 (uniform error of width 1)."""

INTEGER_TOL = 1e-3
"""Samples within this of an integer are taken as digitised integers (quantisation present)."""

RANGE_TREND_Z = 3.0
"""A range-correction table is kept only if some bin differs from the pooled median by more
than this many standard errors (otherwise: no trend, docs/method.md §(f))."""

RANGE_GATE_M = 1.0
"""Pulses whose own CFD range differs from the DR range by more than this (m) are treated as
different echoes and left out of the range-correction fit and the CFD check."""

CFD_CHECK_M = 0.10
"""The paper's CFD criterion: |DR range - CFD range| < 0.10 m for > 95 % of pulses (docs/method.md §(f))."""


@dataclass(frozen=True)
class CFDParams:
    """Constant fraction discriminator of docs/method.md §(f).

    The CFD signal is ``y(t) = fraction * x(t) - x(t - delay_ns)`` on the noise-subtracted
    waveform ``x`` upsampled to :data:`FINE_NS`; an echo is a + to - zero crossing of ``y``
    once ``x`` exceeds ``arming_sd`` noise SDs (see :func:`waveforest.sensor.detect_echoes`).
    With this sign convention and the defaults (fraction 0.5, delay = FWHM / 2) the crossing
    of a Gaussian echo of the system width falls exactly on its peak:
    ``t_c = mu + delay / 2 + s**2 ln(fraction) / delay`` (s = Gaussian SD).

    Attributes
    ----------
    fraction : float
        CFD fraction f, 0 < f <= 1.
    delay_ns : float or None
        CFD delay, ns (rounded to the 0.05-ns grid); None = half the system pulse FWHM.
    arming_sd : float
        Arming threshold above the noise mean, in noise SDs.
    dead_time_ns : float or None
        Shortest time between two echoes, ns; None = the system pulse FWHM.
    """

    fraction: float = 0.5
    delay_ns: float | None = None
    arming_sd: float = 4.0
    dead_time_ns: float | None = None

    def __post_init__(self):
        if not (0.0 < self.fraction <= 1.0):
            raise ValueError(f"CFD fraction must lie in (0, 1], got {self.fraction}")
        if self.delay_ns is not None and not self.delay_ns > 0:
            raise ValueError(f"CFD delay_ns must be > 0, got {self.delay_ns}")
        if not self.arming_sd >= 0:
            raise ValueError(f"CFD arming_sd must be >= 0, got {self.arming_sd}")
        if self.dead_time_ns is not None and not self.dead_time_ns >= 0:
            raise ValueError(f"CFD dead_time_ns must be >= 0, got {self.dead_time_ns}")

    @property
    def is_resolved(self) -> bool:
        """True when delay and dead time are numbers (not tied to a pulse width)."""
        return self.delay_ns is not None and self.dead_time_ns is not None

    def resolved(self, fwhm_ns: float | None) -> CFDParams:
        """Fill the pulse-width defaults: delay = FWHM / 2, dead time = FWHM."""
        if self.is_resolved:
            return self
        if fwhm_ns is None or not np.isfinite(fwhm_ns) or fwhm_ns <= 0:
            raise ValueError(
                "CFD delay_ns/dead_time_ns are None (tied to the pulse width): pass the "
                f"system pulse FWHM (got {fwhm_ns!r}) or set them explicitly")
        return replace(
            self,
            delay_ns=0.5 * fwhm_ns if self.delay_ns is None else self.delay_ns,
            dead_time_ns=float(fwhm_ns) if self.dead_time_ns is None else self.dead_time_ns,
        )

    def fine_delay(self) -> int:
        """The delay in fine-grid steps (at least 1)."""
        return max(1, int(round(self.delay_ns / FINE_NS)))

    def fine_dead(self) -> int:
        """The dead time in fine-grid steps."""
        return int(round(self.dead_time_ns / FINE_NS))

    def to_dict(self) -> dict:
        """fraction, delay_ns, arming_sd, dead_time_ns (as a calibration JSON stores them)."""
        return {"fraction": self.fraction, "delay_ns": self.delay_ns, "arming_sd": self.arming_sd,
                "dead_time_ns": self.dead_time_ns}

    @classmethod
    def from_dict(cls, d: dict) -> CFDParams:
        """Inverse of :meth:`to_dict`."""
        return cls(fraction=float(d["fraction"]), delay_ns=d.get("delay_ns"), arming_sd=float(d["arming_sd"]),
                   dead_time_ns=d.get("dead_time_ns"))


@dataclass(frozen=True)
class FeatureParams:
    """First-echo feature settings of docs/method.md §(h).

    Attributes
    ----------
    segment_sd : float
        Segment threshold above the noise mean, in noise SDs.
    peak_rise_sd : float
        A local maximum counts as a peak if it rises (and falls) by this many noise SDs
        relative to the adjacent minima (the segment ends count as threshold-level minima).
    echo_search_ns : float
        Largest distance from the echo time to the nearest sample above the threshold, ns.
    decomposition : bool
        Also the multi-echo features of the Gaussian decomposition (:data:`DECOMPOSITION_FEATURES`).
    """

    segment_sd: float = 3.0
    peak_rise_sd: float = 2.0
    echo_search_ns: float = ECHO_SEARCH_NS
    decomposition: bool = False

    def __post_init__(self):
        for name in ("segment_sd", "peak_rise_sd", "echo_search_ns"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"feature parameter {name} must be >= 0, got {getattr(self, name)}")
