"""The config schema is the one source of defaults: the vegetation builder's are the schema's."""

import inspect

import pytest

from waveforest.config import schema
from waveforest.vegetation.build import build, build_scene


@pytest.mark.parametrize("func", [build, build_scene])
@pytest.mark.parametrize("name", ["ground_rho", "lai_jitter"])
def test_builder_defaults_are_the_schema_defaults(func, name):
    want = schema()["properties"]["vegetation"]["properties"][name]["default"]
    assert inspect.signature(func).parameters[name].default == want, (func.__name__, name)
