"""The forward model: a vegetation instance and beams -> sigma(t) -> waveforms -> echoes -> features.

- :mod:`.forward` -- :class:`~.forward.SensorSetup`, :class:`~.forward.MCRTSetup`,
  :func:`~.forward.trace_and_render`, :func:`~.forward.render_sigma`, :func:`~.forward.twin_echoes`,
  :func:`~.forward.split_effects` (docs/method.md §(c), §(f), §(h)); one code path for the
  ``simulate``, ``sensitivity``, ``sensor-study`` and ``diagnose`` stages;
  :class:`~.forward.SensorSettings`, the config's sensor model before a calibration completes it.
- :mod:`.selection` -- :class:`~.selection.SelectRules`, :func:`~.selection.select_pulses`: the
  pulses that hit field samples and their flags (docs/method.md §(i1), i4).
- :mod:`.simulate` -- :class:`~.simulate.SimulateSettings`, :func:`~.simulate.plan`,
  :func:`~.simulate.simulate_pulses`: simulated twins of selected real pulses (docs/method.md §(i1)).
- :mod:`.calibration_pulses` -- the calibration targets' pulses of an AGC-normalised pulse table
  (docs/method.md §(e)).
- :mod:`.agc_fit` -- Eq. 1 fitted on a pulse table's target pulses, and the table normalised by it
  (docs/method.md §(b)).
- :mod:`.features` -- feature tables of pulse files, streamed in batches (docs/method.md §(h)).
- :mod:`.self_tuning` -- the CFD tuned on a file's own DR echoes (``tune-cfd``).

The settings dataclasses are built from the validated config by :mod:`waveforest.settings`.

Seeds of the model come from :mod:`waveforest.rng` (hashed parts).
"""
