"""The reference sensor of the sensitivity and sensor studies (docs/method.md §(i2), i3).

The paper uses the calibrated S(t) of dataset 2010_12_1. When that calibration is at hand
(``results/calibration/2010_12_1.parquet`` + ``.json``) it is used with its noise; otherwise an
analytic Gaussian S(t) of ``sensitivity.reference_system.fwhm_ns`` whose scale makes a
nadir Lambertian plane of HDRF ``plane_hdrf`` at ``range_m`` peak at ``plane_dn`` DN above
the noise (a spike sigma = HDRF / pi in one bin: peak = S_peak HDRF / (pi R^2), Eq. 7).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from waveforest.errors import WaveforestError
from waveforest.sensor.calibration import load_calibration
from waveforest.sensor.system_waveform import gaussian_system_waveform, load_system_waveform


@dataclass(frozen=True)
class ReferenceSystem:
    """The configured reference sensor (config ``sensitivity.reference_system``).

    Attributes
    ----------
    fwhm_ns : float, ns
        FWHM of the analytic Gaussian S(t).
    plane_hdrf : float
        HDRF of the nadir Lambertian plane that fixes the Gaussian's scale.
    plane_dn : float, DN
        Peak of that plane's echo above the noise mean.
    noise_mean, noise_sd : float, DN
        Noise of the Gaussian S(t), and of a calibrated S(t) without its calibration JSON.
    """

    fwhm_ns: float
    plane_hdrf: float
    plane_dn: float
    noise_mean: float
    noise_sd: float


@dataclass(frozen=True)
class ReferenceSensor:
    """S(t) and noise of the studies, and where they came from."""

    system: object
    noise_mean: float
    noise_sd: float
    source: str


def reference_sensor(ref: ReferenceSystem, system_path=None, calibration_path=None,
                     range_m: float = 1200.0) -> ReferenceSensor:
    """S(t) and noise from a calibration, or the configured Gaussian (see module docstring).

    Parameters
    ----------
    ref : ReferenceSystem
    system_path : path or None
        Calibrated S(t) (Parquet). None or empty -> the Gaussian; a missing file is an error.
    calibration_path : path or None
        JSON with noise_mean and noise_sd; default: ``system_path`` with suffix ``.json``.
    range_m : float
        Range at which ``plane_dn`` holds, m (Gaussian only).
    """

    if system_path is not None and str(system_path).strip():
        system_path = Path(system_path)
        if not system_path.exists():
            raise WaveforestError(f"{system_path}: no such file (omit --system for the Gaussian S(t))")
        system = load_system_waveform(system_path)
        cal = Path(calibration_path) if calibration_path else system_path.with_suffix(".json")
        if cal.exists():
            c = load_calibration(cal)
            return ReferenceSensor(system, c.noise_mean, c.noise_sd,
                                   f"calibrated S(t) {system_path.name}, noise {cal.name}")
        return ReferenceSensor(system, float(ref.noise_mean), float(ref.noise_sd),
                               f"calibrated S(t) {system_path.name}, configured noise")
    peak = float(ref.plane_dn) * math.pi * float(range_m) ** 2 / float(ref.plane_hdrf)
    system = gaussian_system_waveform(float(ref.fwhm_ns), peak)
    return ReferenceSensor(system, float(ref.noise_mean), float(ref.noise_sd),
                           f"Gaussian S(t), FWHM {float(ref.fwhm_ns):g} ns")
