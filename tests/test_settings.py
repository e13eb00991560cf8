"""Typed settings: the builders of waveforest.settings and the schema as the one source of defaults."""

from __future__ import annotations

import dataclasses
import inspect

import pytest

from waveforest import config, settings
from waveforest.analysis.classify import ClassifySettings
from waveforest.analysis.compare import CompareSettings
from waveforest.model.agc_fit import AGCSettings
from waveforest.model.forward import MCRTSetup, SensorSettings, SensorSetup
from waveforest.model.selection import SelectRules
from waveforest.model.simulate import SimulateSettings
from waveforest.sensor import gaussian_system_waveform
from waveforest.sensor.params import CFDParams, FeatureParams
from waveforest.sensor.reference import ReferenceSystem, reference_sensor

LIBRARY_DEFAULTS = {
    (SelectRules, "tree_radius_m"): "select/tree_radius_m",
    (SelectRules, "tree_min_echo_h_m"): "select/tree_min_echo_h_m",
    (SelectRules, "min_pulses"): "select/min_pulses",
    (SelectRules, "comparison_species"): "simulate/species",
    (SelectRules, "height_range_m"): "simulate/height_range_m",
    (CFDParams, "fraction"): "sensor/cfd/fraction",
    (CFDParams, "delay_ns"): "sensor/cfd/delay_ns",
    (CFDParams, "arming_sd"): "sensor/cfd/arming_sd",
    (CFDParams, "dead_time_ns"): "sensor/cfd/dead_time_ns",
    (FeatureParams, "segment_sd"): "sensor/features/segment_sd",
    (FeatureParams, "peak_rise_sd"): "sensor/features/peak_rise_sd",
    (FeatureParams, "echo_search_ns"): "sensor/features/echo_search_ns",
    (FeatureParams, "decomposition"): "sensor/features/decomposition",
}
"""(dataclass, field) with a default -> the schema key whose default it restates."""

NO_CONFIG_DEFAULTS = {
    (SensorSetup, "render_effects"), (SensorSetup, "range_correction"), (MCRTSetup, "effects"),
}
"""Defaults that no config key holds (effects off, no range correction)."""


def schema_default(path: str):
    node = config.schema()
    for part in path.split("/"):
        node = node["properties"][part]
    return node["default"]


def _plain(value):
    """Tuples as lists, recursively (the schema's YAML has lists)."""
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    return value


@pytest.mark.parametrize(("cls", "name"), sorted(LIBRARY_DEFAULTS, key=lambda k: (k[0].__name__, k[1])))
def test_a_library_default_is_the_schemas(cls, name):
    f = next(f for f in dataclasses.fields(cls) if f.name == name)
    value = f.default_factory() if f.default is dataclasses.MISSING else f.default
    assert _plain(value) == schema_default(LIBRARY_DEFAULTS[cls, name])


@pytest.mark.parametrize("cls", [SelectRules, CFDParams, FeatureParams, SensorSetup, SensorSettings, MCRTSetup,
                                 SimulateSettings, ReferenceSystem, AGCSettings, ClassifySettings,
                                 CompareSettings])
def test_every_library_default_is_checked(cls):
    for f in dataclasses.fields(cls):
        if f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING:
            assert (cls, f.name) in LIBRARY_DEFAULTS or (cls, f.name) in NO_CONFIG_DEFAULTS, (cls, f.name)


def test_reference_range_default_is_the_schemas():
    default = inspect.signature(reference_sensor).parameters["range_m"].default
    assert default == schema_default("sensitivity/range_m")


def test_builders_of_the_default_config_give_the_library_defaults():
    cfg = config.load(None)
    assert settings.select_rules(cfg) == SelectRules()
    assert settings.cfd_params(cfg) == CFDParams()
    assert settings.feature_params(cfg) == FeatureParams()


def test_simulate_settings():
    cfg = config.load(overrides={"seed": 7, "mcrt": {"n_rays": 123},
                                 "simulate": {"instances_per_sample": None, "max_pulses": None,
                                              "effects": {"hotspot": 1.2}},
                                 "vegetation": {"ground_rho": 0.25}})
    s = settings.simulate_settings(cfg)
    assert (s.seed, s.max_pulses, s.instances_per_sample) == (7, None, None)
    assert s.species == tuple(cfg["simulate"]["species"])
    assert dict(s.effects) == {"hotspot": 1.2}
    assert (s.ground_rho, s.lai_jitter) == (0.25, cfg["vegetation"]["lai_jitter"])
    assert s.mcrt == settings.mcrt_setup(cfg) and s.mcrt.n_rays == 123 and s.mcrt.effects == {}
    assert s.sensor == settings.sensor_settings(cfg)


def test_mcrt_setup_rays_and_effects():
    cfg = config.load(None)
    m = settings.mcrt_setup(cfg, n_rays=None, effects={"specular": 0.1})
    assert m.n_rays == cfg["mcrt"]["n_rays"] and m.kwargs()["specular"] == 0.1
    assert settings.mcrt_setup(cfg, n_rays=50).kwargs()["n_rays"] == 50


def test_sensor_setup_resolves_the_cfd_on_the_system_width():
    cfg = config.load(overrides={"sensor": {"digitizer_max": 1023}})
    system = gaussian_system_waveform(4.0, 1e8)
    setup = settings.sensor_setup(cfg, system, 10.0, 1.5, 1.0, render_effects={"nonlinearity": 200.0})
    assert setup.digitizer_max == 1023 and setup.render_effects == {"nonlinearity": 200.0}
    assert setup.cfd.delay_ns == pytest.approx(0.5 * system.fwhm_ns)
    assert setup.cfd.dead_time_ns == pytest.approx(system.fwhm_ns)
    wide = gaussian_system_waveform(8.0, 1e8)
    other = setup.with_system(wide, settings.cfd_params(cfg))
    assert other.cfd.delay_ns == pytest.approx(0.5 * wide.fwhm_ns) and other.noise_sd == setup.noise_sd
    fixed = CFDParams(delay_ns=3.0, dead_time_ns=5.0)
    assert settings.sensor_setup(cfg, system, 10.0, 1.5, 1.0, cfd=fixed).cfd == fixed


def test_reference_system():
    cfg = config.load(overrides={"sensitivity": {"reference_system": {"fwhm_ns": 5.0}}})
    ref = settings.reference_system(cfg)
    assert ref.fwhm_ns == 5.0 and ref.noise_sd == cfg["sensitivity"]["reference_system"]["noise_sd"]
    assert reference_sensor(ref).source.startswith("Gaussian S(t), FWHM 5 ns")


def test_agc_classify_and_compare_settings():
    cfg = config.load(overrides={"seed": 3, "agc": {"b": 0.01, "b_bounds": [0, 0.04]},
                                 "classify": {"extra_feature_sets": [["E", "FWHM"]]},
                                 "simulate": {"compare_min_h_m": {"birch": 2}}})
    agc = settings.agc_settings(cfg)
    assert (agc.b, agc.b_bounds, agc.statistic) == (0.01, (0, 0.04), cfg["agc"]["statistic"])
    assert (agc.noise_tail, agc.digitizer_max) == (cfg["calibrate"]["noise_tail"], cfg["sensor"]["digitizer_max"])
    assert settings.agc_settings(config.load(None)).b is None
    c = settings.classify_settings(cfg)
    assert c.extra_feature_sets == (("E", "FWHM"),) and c.seed == 3
    assert c.min_pulses == cfg["select"]["min_pulses"] and c.groups == tuple(cfg["classify"]["groups"])
    m = settings.compare_settings(cfg)
    assert m.min_h_m == {"birch": 2.0} and m.species == tuple(cfg["simulate"]["species"]) and m.seed == 3
