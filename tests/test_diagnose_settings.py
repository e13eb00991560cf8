"""The diagnosis's typed settings: every default is the schema's, and one builder reads the config."""

from __future__ import annotations

from dataclasses import fields

import pytest

from waveforest import config
from waveforest.diagnose import gap as G
from waveforest.diagnose.power import PowerSettings
from waveforest.diagnose.search import SearchSettings
from waveforest.effects import CATALOGUE
from waveforest.settings import diagnose_settings

SEARCH_KEYS = {"rounds": "rounds", "n_boot": "bootstrap", "values": "values", "refine": "refine",
               "replicates": "pulses_per_value", "alpha": "alpha", "min_relative_reduction": "min_relative_reduction",
               "candidates": "candidates", "refit": "refit", "crossfit": "crossfit", "features": "features",
               "min_pulses": "min_cell_pulses", "min_samples": "min_cell_samples", "signature_alpha": "signature_alpha"}
"""SearchSettings field -> key of the config section ``diagnose`` (``floors`` is no config key)."""


def _schema_default(*path):
    node = config.schema()
    for key in path:
        node = node["properties"][key]
    value = node["default"]
    return tuple(value) if isinstance(value, list) else value


def _field_default(cls, name):
    return next(f.default for f in fields(cls) if f.name == name)


def test_search_settings_defaults_are_the_schemas():
    # floors and floor_scale are not config keys (floor_scale: calibrated by the diagnosis)
    assert set(SEARCH_KEYS) | {"floors", "floor_scale"} == {f.name for f in fields(SearchSettings)}
    for name, key in SEARCH_KEYS.items():
        want = _schema_default("diagnose", key)
        if key == "candidates":  # null: the whole catalogue
            assert want is None
            want = tuple(CATALOGUE)
        assert _field_default(SearchSettings, name) == want, name
    assert _field_default(SearchSettings, "floors") is None
    assert _field_default(SearchSettings, "floor_scale") == 1.0


def test_power_settings_and_cell_minima_defaults_are_the_schemas():
    for f in fields(PowerSettings):
        assert f.default == _schema_default("diagnose", "power", f.name), f.name
    assert G.MIN_CELL_PULSES == _schema_default("diagnose", "min_cell_pulses")
    assert G.MIN_CELL_SAMPLES == _schema_default("diagnose", "min_cell_samples")


def test_the_default_study_builds_the_default_settings():
    s = diagnose_settings(config.load())
    assert s.search == SearchSettings() and s.power == PowerSettings()
    cfg = config.load()
    assert s.datasets == tuple(d for d in cfg["simulate"]["datasets"] if d in cfg["datasets"])
    assert s.seed == cfg["seed"] and dict(s.base_effects) == {} and s.fit_pulses is None


def test_the_base_models_effects_are_no_candidates_and_the_chain_is_the_diagnosiss():
    cfg = config.load(overrides={"simulate": {"effects": {"hotspot": 1.3}},
                                 "diagnose": {"datasets": ["2012_10_1"], "n_rays": 512, "instances_per_sample": None,
                                              "power": {"replicates": 2}}})
    s = diagnose_settings(cfg)
    assert "hotspot" not in s.search.candidates and len(s.search.candidates) == len(CATALOGUE) - 1
    assert dict(s.base_effects) == {"hotspot": 1.3} and s.datasets == ("2012_10_1",)
    assert s.power == PowerSettings(replicates=2)
    assert s.strata.rules.tree_min_echo_h_m == cfg["select"]["tree_min_echo_h_m"]
    assert dict(s.strata.compare_min_h_m) == pytest.approx(cfg["simulate"]["compare_min_h_m"])
