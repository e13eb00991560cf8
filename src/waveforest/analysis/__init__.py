"""The paper's analyses as a library: typed settings in, tables out; the stages do the file I/O.

- :mod:`.compare` -- real vs simulated first-echo features: Table 3, the order checks and the
  data of Figs. 6-7 (docs/method.md §(i1)); :class:`~.compare.CompareSettings`. It reads the Fig. 7
  waveforms from their pulse tables by path, only the rows it draws.
- :mod:`.classify` -- the real-data LDA of four functional groups, Table 4 (docs/method.md §(i4));
  :class:`~.classify.ClassifySettings`.
- :mod:`.sensitivity` -- simulated birch Apeak against vegetation parameters, Fig. 8 (docs/method.md §(i2)).
- :mod:`.sensor_study` -- the sensor study, Fig. 9 (docs/method.md §(i3)).

The settings dataclasses are built from the validated config by :mod:`waveforest.settings`.
"""
