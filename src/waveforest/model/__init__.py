"""The forward model: a vegetation instance and beams -> sigma(t) -> waveforms -> echoes -> features.

- :mod:`.forward` -- :class:`~.forward.SensorSetup`, :class:`~.forward.MCRTSetup`,
  :func:`~.forward.trace_and_render`, :func:`~.forward.render_sigma`, :func:`~.forward.twin_echoes`,
  :func:`~.forward.split_effects` (docs/method.md §(c), §(f), §(h)); one code path for the
  ``simulate``, ``sensitivity``, ``sensor-study`` and ``diagnose`` stages.

Seeds of the model come from :mod:`waveforest.rng` (hashed parts).
"""
