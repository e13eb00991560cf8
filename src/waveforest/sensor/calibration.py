"""System-waveform calibration from reference targets, Eq. 8 (docs/method.md §(e)).

For a near-level planar target sigma(t) is a single spike of ``sigma = HDRF / pi`` per unit
power (times cos(incidence) if ``calibrate.cos_incidence``), so each target pulse gives

    S_i(t) = (V_i(t) - c-bar) * R_i^2 / sigma_i                                      (8)

with V_i the AGC-normalised waveform, aligned so that t = 0 is the pulse's first DR echo time
(``echo_time_ns[0]``), and R_i its range. S(t) on the 0.05-ns grid is the mean of S_i over all
pulses of all calibration targets (equal weight per sample), its spread the SD of the pulses'
samples about it, by equivalent-time sampling: each recorded sample lies at its own time after
the echo (the pulses' echo times fall at random within a sample interval), and it counts towards the grid
times within :data:`KERNEL_NS` of it with triangular weights. Interpolating each pulse linearly
between its samples instead would smooth S(t) by a triangle of one sampling interval's
half-width (variance dt^2 / 6 at dt = 1 ns: a 7.2-ns FWHM becomes 7.26 ns); the kernel's
variance is KERNEL_NS^2 / 6, four times smaller (7.22 ns), and it averages enough samples per
grid time to keep S(t)'s noise below that of the interpolated mean (docs/validation.md,
Calibration). Grid times no sample comes near (pulses that share one phase) are
interpolated linearly between their neighbours. c-bar and the noise SD come from the last
``calibrate.noise_tail`` samples of the same pulses, taken on the recorded values (the AGC
normalisation is undone for the tails: the AGC does not change the noise).

Pulses whose recorded peak reaches the digitiser maximum (clipped) or whose incidence zenith
exceeds ``calibrate.max_zenith_deg`` are left out.

Sensor effects of the simulation model (``simulate.effects``, src/waveforest/effects.py) that
also act on the targets' waveforms are inverted before Eq. 8, so that S(t) is the system
waveform of the model that will use it (:func:`linearise`): the detector saturation
``nonlinearity`` L (the signal model's ``V - c-bar = L tanh(v / L)``; each pulse at L / g, g its
AGC gain, as the saturation acts after the gain) and ``trigger_loss`` f
(the earliest fraction f of a target's near-delta sigma is lost, which scales its whole echo
by 1 - f). Without them a model with the effect would apply it twice: once through S(t), once
in the signal model. ``diagnose`` recalibrates in the same way for each value it tries
(:class:`waveforest.model.calibration_pulses.CalibrationPulses`).

The same stage sets the CFD against the DR ranges (docs/method.md §(f)) on the target pulses
(calibration and AGC targets) and ``calibrate.cfd_pulses`` pulses drawn at random from the
dataset (seeded), whose echoes span the widths of ground and vegetation: it tunes the CFD
fraction and delay (``calibrate.tune_cfd``; cfd_tuning.py), fits the amplitude-dependent range
correction dR(Apeak) on all of them (:func:`fit_range_correction`), and reports the paper's
check (the fraction with |dR| < 0.10 m and the bias) on the target pulses before and after the
correction. The JSON keeps the CFD with its correction (:func:`cfd_of`): every stage that
detects echoes with this calibration uses that pair.

A written calibration is read back as one typed :class:`Calibration` (S(t), noise, CFD, range
correction and the whole JSON) by :func:`load_calibration`; :func:`waveforest.io.results.read_calibration_json`
gives the checked JSON alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

import waveforest.sensor.checks as checks
from waveforest.io.results import read_calibration_json
from waveforest.sensor.cfd import RangeCorrection
from waveforest.sensor.params import CFD_CHECK_M, FINE_NS, RANGE_GATE_M, CFDParams
from waveforest.sensor.system_waveform import SystemWaveform, load_system_waveform

_CHUNK = 2048
"""Pulses per block of the vectorised accumulation (bounds memory to ~CHUNK x samples x kernel)."""

KERNEL_NS = 0.5
"""Half-width of the triangular kernel by which a recorded sample counts towards S(t)'s grid
times (module docstring), ns: smoothing variance KERNEL_NS^2 / 6."""


def calibration_grid(window_ns=(-20.0, 60.0)) -> np.ndarray:
    """The 0.05-ns time grid of S(t) over ``window_ns`` relative to the echo time (t = 0 on it)."""
    lo, hi = float(window_ns[0]), float(window_ns[1])
    if not lo < 0 < hi:
        raise ValueError(f"window_ns must straddle 0 (lo < 0 < hi), got {window_ns}")
    return FINE_NS * np.arange(math.ceil(lo / FINE_NS - 1e-9), math.floor(hi / FINE_NS + 1e-9) + 1)


LINEARISE_MAX = 3.0
""":func:`linearise` caps the linearised signal at this many saturation levels L: beyond it
``tanh`` lies within 0.5 % of 1, and a recorded value there no longer tells the input."""


def linearise(v, nonlinearity=0.0, trigger_loss: float = 0.0) -> np.ndarray:
    """Planar-target signal above the noise mean with the sensor effects inverted, DN.

    ``L artanh(v / L) / (1 - f)``: the inverse of the signal model's saturation
    ``v -> L tanh(v / L)`` (L = ``nonlinearity``, a scalar or an array broadcast against ``v``,
    e.g. one level per pulse as a column; 0 = linear; capped at ``LINEARISE_MAX`` L) and of the
    loss of the earliest fraction f = ``trigger_loss`` of a near-delta sigma (the echo scaled
    by 1 - f). NaN stays NaN.
    """
    v = np.asarray(v, dtype=np.float64)
    level = np.asarray(nonlinearity, dtype=np.float64)
    if not np.all(level >= 0):
        raise ValueError(f"nonlinearity (saturation level, DN) must be >= 0, got {nonlinearity}")
    if not 0.0 <= trigger_loss < 1.0:
        raise ValueError(f"trigger_loss must be in [0, 1), got {trigger_loss}")
    if np.any(level > 0):
        lim = math.tanh(LINEARISE_MAX)
        safe = np.where(level > 0, level, 1.0)
        v = np.where(level > 0, safe * np.arctanh(np.clip(v / safe, -lim, lim)), v)
    return v / (1.0 - trigger_loss) if trigger_loss else v


def calibrate_system_waveform(samples, lengths, sampling_ns, echo_time_ns, range_m, sigma, noise_mean, *,
                              window_ns=(-20.0, 60.0), nonlinearity=0.0,
                              trigger_loss: float = 0.0) -> SystemWaveform:
    """S(t) by Eq. 8 averaged over planar-target pulses (docs/method.md §(e)).

    Parameters
    ----------
    samples : (n, n_s) DN, AGC-normalised waveforms.  lengths : (n,).
    sampling_ns : float or (n,), ns.  echo_time_ns : (n,) first DR echo, ns from the first sample.
    range_m : (n,) m.  sigma : (n,) target cross-section per unit power (HDRF/pi [x cos]).
    noise_mean : float, c-bar, DN.  window_ns : (lo, hi) time span of S(t) around the echo.
    nonlinearity, trigger_loss : sensor effects of the model, inverted on each pulse before
        Eq. 8 (:func:`linearise`); 0 = off; nonlinearity a scalar or (n,) levels per pulse, DN.

    Returns
    -------
    SystemWaveform with s = mean over pulses and s_sd = SD of their samples about it (NaN with < 2 pulses);
    meta n_pulses.
    """
    x, lens = checks.waveforms(samples, lengths)
    n = x.shape[0]
    if n == 0:
        raise ValueError("calibrate_system_waveform: no pulses")
    dt = checks.per_pulse(sampling_ns, n, "sampling_ns", positive=True)
    te = checks.per_pulse(echo_time_ns, n, "echo_time_ns")
    r = checks.per_pulse(range_m, n, "range_m", positive=True)
    sg = checks.per_pulse(sigma, n, "sigma", positive=True)
    level = checks.per_pulse(nonlinearity, n, "nonlinearity", nonnegative=True)
    t = calibration_grid(window_ns)
    if not (te.max() >= -t[0] and np.max((lens - 1) * dt - te) >= t[-1]):
        raise ValueError("calibrate_system_waveform: some times of the window lie outside every record; "
                         "narrow calibrate.window_ns")
    sums = np.zeros((3, t.size))
    k = np.arange(x.shape[1])
    for start in range(0, n, _CHUNK):  # blocks of pulses, each vectorised
        sl = slice(start, start + _CHUNK)
        tau = k[None, :] * dt[sl, None] - te[sl, None]  # each sample's time after the echo, ns
        ok = k[None, :] < lens[sl, None]
        si = linearise(x[sl] - noise_mean, level[sl, None], trigger_loss) * (r[sl] ** 2 / sg[sl])[:, None]
        ok &= np.isfinite(si) & (tau > t[0] - KERNEL_NS) & (tau < t[-1] + KERNEL_NS)
        _accumulate(sums, tau[ok], si[ok], t[0])
    w, s1, s2 = sums
    cov = w > 0
    mean = np.interp(t, t[cov], s1[cov] / w[cov])
    var = np.interp(t, t[cov], np.maximum(s2[cov] / w[cov] - (s1[cov] / w[cov]) ** 2, 0.0))
    sd = np.sqrt(var) if n >= 2 else np.full(t.size, np.nan)
    meta = {"n_pulses": int(n)}
    if level.any() or trigger_loss:
        meta.update(nonlinearity=float(np.median(level)), trigger_loss=float(trigger_loss))
    return SystemWaveform(t, mean, sd, meta)


def _accumulate(sums: np.ndarray, tau: np.ndarray, v: np.ndarray, t0: float) -> None:
    """Add samples ``v`` at times ``tau`` (ns after the echo) to ``sums`` ((3, K): weight,
    weighted sum, weighted sum of squares over the grid ``t0 + FINE_NS * j``), each with the
    triangular weight max(0, 1 - |t_j - tau| / KERNEL_NS)."""
    m = int(math.ceil(KERNEL_NS / FINE_NS))
    size = sums.shape[1]
    j0 = np.rint((tau - t0) / FINE_NS).astype(np.int64)
    for o in range(-m, m + 1):
        j = j0 + o
        w = np.maximum(0.0, 1.0 - np.abs(t0 + j * FINE_NS - tau) / KERNEL_NS)
        keep = (j >= 0) & (j < size) & (w > 0)
        for row, val in enumerate((w, w * v, w * v * v)):
            sums[row] += np.bincount(j[keep], val[keep], minlength=size)


def cfd_check(dr_minus_cfd_m) -> dict:
    """The paper's CFD criterion on dR = DR range - CFD range, m (gated at RANGE_GATE_M)."""
    d = np.asarray(dr_minus_cfd_m, dtype=np.float64)
    d = d[np.isfinite(d) & (np.abs(d) < RANGE_GATE_M)]
    if d.size == 0:
        return {"n": 0, "frac_within_0_10_m": None, "bias_m": None, "sd_m": None}
    return {"n": int(d.size), "frac_within_0_10_m": float(np.mean(np.abs(d) < CFD_CHECK_M)),
            "bias_m": float(d.mean()), "sd_m": float(d.std(ddof=1)) if d.size > 1 else 0.0}


CALIBRATION_EFFECTS = ("nonlinearity", "trigger_loss")
"""Sensor effects that also shape the calibration targets' waveforms (:func:`linearise`)."""


def calibration_effects(effects: dict | None) -> dict:
    """The switched-on effects of ``effects`` that the calibration inverts (nonlinearity, trigger_loss)."""
    effects = effects or {}
    return {k: float(effects[k]) for k in CALIBRATION_EFFECTS if effects.get(k)}


def cfd_of(meta: dict) -> CFDParams | None:
    """The CFD a calibration JSON dict's range correction was fitted with (None if absent: older files)."""
    c = meta.get("cfd")
    return CFDParams.from_dict(c) if c else None


def range_correction_of(meta: dict) -> RangeCorrection:
    """The range correction stored in a calibration JSON dict (identity if absent)."""
    return RangeCorrection.from_dict(meta.get("range_correction"))


@dataclass(frozen=True)
class Calibration:
    """A dataset's calibration, as the ``calibrate`` stage wrote it (docs/method.md §(e), §(f)).

    Attributes
    ----------
    system : SystemWaveform or None
        S(t), DN m^2 per unit sigma (Eq. 8); None when loaded without its Parquet file.
    noise_mean, noise_sd : float
        c-bar and the noise SD, DN.
    range_correction : RangeCorrection or None
        dR(Apeak) of the CFD; None = identity (none fitted, or absent from the file).
    cfd : CFDParams or None
        The CFD the range correction was fitted with; None = the config's ``sensor.cfd``.
    meta : dict
        The whole calibration JSON (dataset, fwhm_ns, AGC fit, CFD check, ...); empty when
        built in memory.
    """

    system: SystemWaveform | None
    noise_mean: float
    noise_sd: float
    range_correction: RangeCorrection | None = None
    cfd: CFDParams | None = None
    meta: dict = field(default_factory=dict, compare=False)

    @property
    def dataset(self) -> str | None:
        """The dataset the calibration belongs to (None when built in memory)."""
        return self.meta.get("dataset")

    def range_correction_or_identity(self) -> RangeCorrection:
        """:attr:`range_correction`, the identity when None."""
        return self.range_correction if self.range_correction is not None else RangeCorrection.identity()


def load_calibration(json_path, system_path=None) -> Calibration:
    """A dataset's :class:`Calibration` from ``calibration/{dataset}.json`` [and ``.parquet``].

    Parameters
    ----------
    json_path : path
        The calibration JSON (noise, CFD, range correction; :func:`read_calibration_json`).
    system_path : path, optional
        The calibrated S(t) (Parquet, :func:`load_system_waveform`); None: ``system`` is None.

    Raises
    ------
    WaveforestError
        As :func:`read_calibration_json` and :func:`load_system_waveform`.
    """
    meta = read_calibration_json(json_path)
    rc = range_correction_of(meta)
    system = None if system_path is None else load_system_waveform(system_path)
    return Calibration(system, float(meta["noise_mean"]), float(meta["noise_sd"]),
                       None if rc.is_identity else rc, cfd_of(meta), meta)
