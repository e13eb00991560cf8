"""The sensor model and waveform processing, pure (docs/method.md §(b), §(c), §(e), §(f), §(h)).

Everything between sigma(t) and a feature table, for real and simulated waveforms alike; no
file I/O beyond the small loaders named here (the stages are in :mod:`waveforest.stages`).

- :mod:`.system_waveform` -- :class:`SystemWaveform`, :func:`gaussian_system_waveform`, :func:`load_system_waveform` (S(t), Eqs. 6-8);
- :mod:`.signal` -- :func:`render`, the signal model of Eq. 7 (convolution, trigger, record
  window, sampling, noise, rounding, clipping; effects noise_autocorr, nonlinearity, trigger_loss);
- :mod:`.noise` -- :func:`noise_stats`, :func:`ar1`;
- :mod:`.cfd`, :mod:`.cfd_tuning` -- :class:`CFDParams`, :func:`detect_echoes`, :func:`fit_range_correction` (§(f));
- :mod:`.features` -- :func:`first_echo_features`, :func:`feature_table` (§(h));
- :mod:`.agc` -- :func:`agc_gain`, :func:`normalise_waveforms`, :func:`normalise_intensity`, :func:`fit_b` (Eq. 1, §(b));
- :mod:`.calibration` -- :func:`calibrate_system_waveform` (Eq. 8, §(e)), the typed
  :class:`Calibration` and its loader :func:`load_calibration`;
- :mod:`.targets` -- :func:`target_membership`, :func:`pulse_targets` (pulses on reference targets);
- :mod:`.reference` -- the reference sensor of the studies (§(i2), §(i3));
- :mod:`.waveforms` -- waveforms aligned on the first echo (Fig. 7);
- :mod:`.params`, :mod:`.checks` -- parameter objects, input checks.
"""

from waveforest.sensor.agc import (
    agc_gain,
    fit_b,
    nested_cv,
    normalise_intensity,
    normalise_pulses,
    normalise_waveforms,
    peak_amplitudes,
)
from waveforest.sensor.calibration import (
    Calibration,
    calibrate_system_waveform,
    cfd_of,
    load_calibration,
    range_correction_of,
)
from waveforest.sensor.cfd import (
    Echoes,
    RangeCorrection,
    apply_range_correction,
    detect_echoes,
    fit_range_correction,
    gaussian_cfd_time,
)
from waveforest.sensor.features import FEATURE_NAMES, feature_table, first_echo_features
from waveforest.sensor.noise import NoiseStats, ar1, noise_stats
from waveforest.sensor.params import CFDParams, FeatureParams
from waveforest.sensor.signal import Rendered, analog_waveforms, apply_trigger_loss, render
from waveforest.sensor.system_waveform import SystemWaveform, gaussian_system_waveform, load_system_waveform
from waveforest.sensor.targets import pulse_targets, target_membership

__all__ = [
    "SystemWaveform", "gaussian_system_waveform", "load_system_waveform",
    "Rendered", "render", "analog_waveforms", "apply_trigger_loss",
    "CFDParams", "Echoes", "detect_echoes", "gaussian_cfd_time",
    "RangeCorrection", "fit_range_correction", "apply_range_correction",
    "FeatureParams", "FEATURE_NAMES", "first_echo_features", "feature_table",
    "agc_gain", "normalise_intensity", "normalise_waveforms", "normalise_pulses", "peak_amplitudes",
    "nested_cv", "fit_b",
    "Calibration", "calibrate_system_waveform", "load_calibration", "cfd_of",
    "range_correction_of",
    "NoiseStats", "noise_stats", "ar1",
    "target_membership", "pulse_targets",
]
