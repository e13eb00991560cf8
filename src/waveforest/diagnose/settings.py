"""Typed settings of the diagnosis (config section ``diagnose`` and the sections it re-runs).

Built from the validated config in one place, :func:`waveforest.settings.diagnose_settings`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from waveforest.diagnose.power import PowerSettings
from waveforest.diagnose.search import SearchSettings
from waveforest.diagnose.strata import StrataSettings
from waveforest.model.simulate import SimulateSettings


@dataclass(frozen=True)
class DiagnoseSettings:
    """Everything the diagnosis reads from the study's config.

    Attributes
    ----------
    datasets : tuple of str
        Datasets diagnosed (``diagnose.datasets``, default the processed comparison datasets).
    seed : int
        The study's master seed.
    base_effects : mapping name -> value
        Effects of the base model (``simulate.effects``).
    search : SearchSettings
        Its candidates leave out the base model's effects.
    power : PowerSettings
    strata : StrataSettings
    simulate : SimulateSettings
        The study's simulation chain with the diagnosis's rays (``diagnose.n_rays``, at most
        ``mcrt.n_rays``) and vegetation instances (``diagnose.instances_per_sample``) and no
        pulse cap; each call replaces its seed (:class:`.twins.StudySimulator`).
    range_correction : bool
        ``sensor.cfd.range_correction``: the calibration's CFD range correction on the twins'
        own CFD echoes.
    fit_pulses : int or None
        ``diagnose.fit_pulses``.
    """

    datasets: tuple[str, ...]
    seed: int
    base_effects: Mapping[str, float]
    search: SearchSettings
    power: PowerSettings
    strata: StrataSettings
    simulate: SimulateSettings
    range_correction: bool
    fit_pulses: int | None
