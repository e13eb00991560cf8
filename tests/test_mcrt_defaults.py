"""The config schema is the one source of defaults: the tracer's defaults are the schema's."""

import inspect

import pytest

from waveforest.config import schema
from waveforest.constants import BIN_NS
from waveforest.mcrt import trace

MCRT_DEFAULTS = ("max_order", "bin_ns", "viewed_diameter_m", "window_ns", "min_rays", "max_rays")
"""Arguments of ``trace`` with a default, each a key of the schema's ``mcrt`` section."""

NO_DEFAULT = ("n_rays", "sampler", "roulette")
"""Arguments of ``trace`` from the schema's ``mcrt`` section that every caller gives."""

OFF_BY_DEFAULT = ("tolerance",)
"""Arguments of ``trace`` that default to off (None): the adaptive budget needs the caller's sensor."""


def _schema_mcrt() -> dict:
    return schema()["properties"]["mcrt"]["properties"]


@pytest.mark.parametrize("name", MCRT_DEFAULTS)
def test_trace_defaults_are_the_schema_defaults(name):
    param = inspect.signature(trace).parameters[name]
    assert param.default == _schema_mcrt()[name]["default"], name


@pytest.mark.parametrize("name", NO_DEFAULT)
def test_trace_has_no_default_for(name):
    assert inspect.signature(trace).parameters[name].default is inspect.Parameter.empty, name


@pytest.mark.parametrize("name", OFF_BY_DEFAULT)
def test_trace_is_off_by_default_for(name):
    assert inspect.signature(trace).parameters[name].default is None, name


def test_every_schema_mcrt_key_is_a_trace_argument():
    assert set(_schema_mcrt()) == set(MCRT_DEFAULTS) | set(NO_DEFAULT) | set(OFF_BY_DEFAULT)


def test_the_fine_time_bin_is_the_schema_default():
    assert BIN_NS == _schema_mcrt()["bin_ns"]["default"]
