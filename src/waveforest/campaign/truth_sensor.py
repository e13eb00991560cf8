"""The virtual ALS60 as it really behaves: from sigma(t) to DR echoes and a recorded waveform.

What the analysis model assumes (docs/method.md §(c), f) and what this sensor does instead:

==========================  ======================================  ==========================================
                            analysis model                          this sensor (the "truth")
==========================  ======================================  ==========================================
system waveform S(t)        calibrated from targets (Eq. 8)         asymmetric, exponential tail, after-pulse
                                                                    (:mod:`.system_pulse`)
gain                        none (simulated WFs have no AGC)        per-pulse AGC from a feedback loop, true
                                                                    gain law of Eq. 1 with the dataset's b
                                                                    (:mod:`.agc_loop`), on the signal only
trigger                     CFD on the sampled waveform             the sensor's own DR discriminator on the
                                                                    0.05-ns analog signal (:mod:`.dr_cfd`)
DR ranges                   CFD time                                discriminator time + amplitude-dependent
                                                                    range walk + timing jitter
DR intensity                --                                      echo peak amplitude (gained) + noise, 8 bit
digitiser                   8 bit, noise mean/SD                    8 bit, noise mean/SD of the dataset
==========================  ======================================  ==========================================

The Eq. 7 convolution itself and the sensor-stage effects (``trigger_loss``, ``nonlinearity``,
``noise_autocorr``; src/waveforest/effects.py) are those of :mod:`waveforest.sensor`, applied
where they act: trigger loss on sigma(t) before anything, saturation on the gained analog
signal (so the DR discriminator, the DR intensity and the AGC loop see it too), AR(1) on the
digitiser noise.

Record: the waveform is triggered by the first DR echo and starts a uniform
``pre_trigger_m`` (3.3-4.8 m of range) before it (docs/method.md §(a)); it is ``record_ns`` (256 ns)
long at the dataset's sampling interval; samples are point samples of the analog signal
(linear interpolation of the 0.05-ns grid) plus noise, rounded and clipped to 0-255.

Random draws per call, in this order, always the same number whatever the effects: record
offsets (n), timing jitter (n, 4), intensity noise (n, 4), noise (n, n_s).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from waveforest.campaign.agc_loop import AGCParams
from waveforest.campaign.dr_cfd import dr_cfd
from waveforest.campaign.system_pulse import TrueSystemWaveform, true_system_waveform
from waveforest.constants import BIN_NS, RANGE_PER_NS, RECORD_NS
from waveforest.sensor.noise import gaussian_noise
from waveforest.sensor.signal import analog_waveforms, sample_analog
from waveforest.sensor.system_waveform import SystemWaveform

MAX_ECHOES = 4
"""DR echoes per pulse (ALS60, docs/method.md §(a))."""

REFERENCE_RHO = 0.30
"""Reflectance of the plane that ``ground_amplitude_dn`` refers to (the model ground, docs/method.md §(g))."""


@dataclass(frozen=True)
class TruthSensor:
    """The true sensor of one dataset (``sensor_truth.csv`` row + Table 2 + config)."""

    dataset: str
    system: TrueSystemWaveform
    agc: AGCParams
    noise_mean_dn: float
    noise_sd_dn: float
    sampling_ns: float
    cfd_fraction: float
    cfd_delay_ns: float
    cfd_arm_dn: float
    cfd_dead_time_ns: float
    walk_coef_m: float
    walk_ref_dn: float
    walk_max_m: float
    timing_jitter_ns: float
    intensity_noise_dn: float
    strip_xy_sd_m: float
    strip_z_sd_m: float
    record_ns: float = RECORD_NS
    pre_trigger_m: tuple[float, float] = (3.3, 4.8)
    digitizer_max: int = 255

    @classmethod
    def from_row(cls, row, *, record_ns: float = RECORD_NS, pre_trigger_m=(3.3, 4.8),
                 digitizer_max: int = 255) -> TruthSensor:
        """The sensor of a row of :func:`waveforest.campaign.params.load_datasets`."""
        fwhm = float(row["pulse_width_fwhm_ns"])
        peak = float(row["ground_amplitude_dn"]) * float(row["mean_range_m"]) ** 2 * np.pi / REFERENCE_RHO
        system = true_system_waveform(
            fwhm, float(row["pulse_tail_ratio"]), float(row["afterpulse_rel"]),
            float(row["afterpulse_delay_fwhm"]), peak, cfd_fraction=float(row["cfd_fraction"]),
            cfd_delay_fwhm=float(row["cfd_delay_fwhm"]))
        lo, hi = (float(v) for v in pre_trigger_m)
        return cls(
            dataset=str(row["dataset"]), system=system, agc=AGCParams.from_row(row),
            noise_mean_dn=float(row["noise_mean_dn"]), noise_sd_dn=float(row["noise_sd_dn"]),
            sampling_ns=float(row["sampling_ns"]), cfd_fraction=float(row["cfd_fraction"]),
            cfd_delay_ns=float(row["cfd_delay_fwhm"]) * fwhm, cfd_arm_dn=float(row["cfd_arm_dn"]),
            cfd_dead_time_ns=float(row["cfd_dead_time_fwhm"]) * fwhm,
            walk_coef_m=float(row["walk_coef_m"]), walk_ref_dn=float(row["walk_ref_dn"]),
            walk_max_m=float(row["walk_max_m"]), timing_jitter_ns=float(row["timing_jitter_ns"]),
            intensity_noise_dn=float(row["intensity_noise_dn"]),
            strip_xy_sd_m=float(row["strip_xy_sd_m"]), strip_z_sd_m=float(row["strip_z_sd_m"]),
            record_ns=float(record_ns), pre_trigger_m=(lo, hi), digitizer_max=int(digitizer_max))

    @property
    def n_samples(self) -> int:
        """Samples per waveform record."""
        return int(round(self.record_ns / self.sampling_ns))

    def system_waveform(self) -> SystemWaveform:
        """S(t) at unit gain as a :class:`waveforest.sensor.SystemWaveform`."""
        return SystemWaveform(self.system.t_ns, self.system.s, meta={"dataset": self.dataset, "truth": True})

    def range_walk_m(self, amplitude_dn) -> np.ndarray:
        """Range walk of a DR echo of peak amplitude ``amplitude_dn`` (DN), m.

        walk = clip(walk_coef_m ln(A / walk_ref_dn), -walk_max_m, walk_max_m); the DR range
        is the true range plus the walk.
        """
        a = np.maximum(np.asarray(amplitude_dn, dtype=np.float64), 1e-6)
        return np.clip(self.walk_coef_m * np.log(a / self.walk_ref_dn), -self.walk_max_m, self.walk_max_m)

    def manifest(self) -> dict:
        """The sensor's parameters for ``truth.json`` (S(t) is stored separately)."""
        return {
            "noise_mean_dn": self.noise_mean_dn, "noise_sd_dn": self.noise_sd_dn,
            "sampling_ns": self.sampling_ns, "record_ns": self.record_ns,
            "pre_trigger_m": list(self.pre_trigger_m), "digitizer_max": self.digitizer_max,
            "pulse_fwhm_ns": self.system.fwhm_ns, "pulse_sigma_ns": self.system.sigma_ns,
            "pulse_tau_ns": self.system.tau_ns, "s_peak_dn_m2": self.system.peak,
            "dr_cfd": {"fraction": self.cfd_fraction, "delay_ns": self.cfd_delay_ns,
                       "arm_dn": self.cfd_arm_dn, "dead_time_ns": self.cfd_dead_time_ns,
                       "max_echoes": MAX_ECHOES},
            "range_walk": {"form": "clip(coef_m * ln(A / ref_dn), -max_m, max_m), added to the range",
                           "coef_m": self.walk_coef_m, "ref_dn": self.walk_ref_dn, "max_m": self.walk_max_m},
            "timing_jitter_ns": self.timing_jitter_ns, "intensity_noise_dn": self.intensity_noise_dn,
            "strip_xy_sd_m": self.strip_xy_sd_m, "strip_z_sd_m": self.strip_z_sd_m,
        }


class Recorded(NamedTuple):
    """What the sensor records for a batch of pulses.

    samples : (n, n_s) uint8, DN. first_sample_ns : (n,) two-way time of sample 0 from
    emission, ns (NaN: no DR echo, nothing recorded). echo_ns : (n, 4) DR echo two-way times
    from emission, ns, NaN-padded (range = time x RANGE_PER_NS). echo_amp_dn : (n, 4) analog
    echo amplitudes (gained). intensity : (n, 4) uint8 DR intensities. n_echoes : (n,) int.
    walk_m : (n, 4) range walk included in each echo's range, m.
    """

    samples: np.ndarray
    first_sample_ns: np.ndarray
    echo_ns: np.ndarray
    echo_amp_dn: np.ndarray
    intensity: np.ndarray
    n_echoes: np.ndarray
    walk_m: np.ndarray


def unit_gain_peaks(sensor: TruthSensor, sigma, t0_ns, range_m, *, trigger_loss: float = 0.0) -> np.ndarray:
    """Peak of each pulse's noise-free analog signal at unit gain, DN (what the AGC loop scales).

    Parameters
    ----------
    sigma : (n, n_bins) float, per-bin sums on the 0.05-ns grid; t0_ns : (n,) ns; range_m : (n,) m.
    """
    analog, _ = analog_waveforms(sigma, t0_ns, range_m, sensor.system_waveform(), trigger_loss=trigger_loss)
    return analog.max(axis=1) if analog.shape[1] else np.zeros(analog.shape[0])


def record(sensor: TruthSensor, sigma, t0_ns, range_m, gain, rng: np.random.Generator, *,
           noise_autocorr: float = 0.0, nonlinearity: float = 0.0, trigger_loss: float = 0.0) -> Recorded:
    """Record a batch of pulses as the real sensor does (module docstring).

    Parameters
    ----------
    sensor : TruthSensor
    sigma : (n, n_bins) float, per-bin sums of sigma per unit emitted power (MCRT output),
        bin 0's left edge at ``t0_ns``.
    t0_ns : (n,) float, two-way time from emission, ns.
    range_m : (n,) float, R of Eq. 7 (range to the beam's ground point), m.
    gain : (n,) float, AGC gain of each pulse (Eq. 1 with the true law).
    rng : numpy.random.Generator
    noise_autocorr, nonlinearity, trigger_loss : sensor-stage effects (off = 0).

    Returns
    -------
    Recorded
    """
    if not isinstance(rng, np.random.Generator):
        raise ValueError("rng must be a numpy.random.Generator")
    sig = np.asarray(sigma, dtype=np.float64)
    n = sig.shape[0]
    analog, t_first = analog_waveforms(sig, t0_ns, range_m, sensor.system_waveform(), gain=gain,
                                       nonlinearity=nonlinearity, trigger_loss=trigger_loss)
    pos, amp, cnt = dr_cfd(analog, fraction=sensor.cfd_fraction, delay_ns=sensor.cfd_delay_ns,
                           arm_dn=sensor.cfd_arm_dn, dead_time_ns=sensor.cfd_dead_time_ns,
                           fwhm_ns=sensor.system.fwhm_ns, max_echoes=MAX_ECHOES)
    lo, hi = sensor.pre_trigger_m
    pre_m = rng.uniform(lo, hi, n)
    jitter = rng.standard_normal((n, MAX_ECHOES)) * sensor.timing_jitter_ns
    inoise = rng.standard_normal((n, MAX_ECHOES)) * sensor.intensity_noise_dn
    noise = gaussian_noise(rng, (n, sensor.n_samples), sensor.noise_mean_dn, sensor.noise_sd_dn, noise_autocorr)

    walk = np.where(np.isfinite(amp), sensor.range_walk_m(np.nan_to_num(amp, nan=1.0)), np.nan)
    echo_ns = (t_first[:, None] + pos * BIN_NS - sensor.system.cfd_offset_ns
               + walk / RANGE_PER_NS + jitter)
    first = echo_ns[:, 0] - pre_m / RANGE_PER_NS
    signal = sample_analog(analog, (first - t_first) / BIN_NS, sensor.sampling_ns / BIN_NS, sensor.n_samples)
    samples = np.clip(np.rint(signal + noise), 0, sensor.digitizer_max).astype(np.uint8)
    intensity = np.where(np.isfinite(amp), np.clip(np.rint(np.nan_to_num(amp) + inoise), 0, 255), 0).astype(np.uint8)
    return Recorded(samples, first, echo_ns, amp, intensity, cnt, walk)
