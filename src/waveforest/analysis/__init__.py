"""The analyses of Hovi & Korpela (2014), METHOD.md (i): one module per stage.

============================  ======================================================  ===================
module                        what                                                    CLI
============================  ======================================================  ===================
:mod:`.campaign_tables`       read/check datasets.csv, fields.csv, targets.csv
:mod:`.select`                pulses whose first echo hits a field sample (i1, i4)    ``select``
:mod:`.simulate`              MCRT + sensor twin of each selected pulse (i1)          ``simulate``
:mod:`.compare`               Table 3, Figs. 6-7 analogues (i1)                       ``compare``
:mod:`.sensitivity`           Fig. 8 analogue: leaf angle, rho, tau, leaf area (i2)   ``sensitivity``
:mod:`.sensor_study`          Fig. 9 analogue: divergence, pulse width, sampling (i3) ``sensor-study``
:mod:`.classify`              Table 4 analogue: four functional groups, LDA (i4)      ``classify``
:mod:`.pulse_sim`             scene -> sigma -> waveform -> echoes -> features
:mod:`.lda`                   LDA, accuracy, kappa, grouped cross-validation
:mod:`.reference`             the reference sensor of the studies (2010_12_1)
:mod:`.plots`                 the figures
:mod:`.paper`                 the paper's Tables 3 and 4 (resources/paper/)
:mod:`.synthetic`             small synthetic pulse tables and analytic scenes (tests)
============================  ======================================================  ===================

Submodules are imported on use (``from waveforest.analysis import select``), so the CLI
stays quick to start.
"""

__all__ = ["campaign_tables", "select", "simulate", "compare", "sensitivity", "sensor_study", "classify",
           "pulse_sim", "lda", "reference", "plots", "paper", "synthetic", "markdown", "waveforms"]
