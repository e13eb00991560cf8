"""Config schema: defaults, validation messages, and agreement with the shipped configs."""

from pathlib import Path

import pytest
import yaml

from waveforest import config

ROOT = Path(__file__).resolve().parents[1]


def test_empty_config_gets_every_default():
    cfg = config.load()
    assert cfg["mcrt"]["n_rays"] == 30000
    assert cfg["mcrt"]["max_order"] == 10
    assert cfg["vegetation"]["ground_rho"] == pytest.approx(0.30)
    assert cfg["sensor"]["cfd"]["fraction"] == pytest.approx(0.5)
    assert len(cfg["datasets"]) == 9


@pytest.mark.parametrize("path", ["config/config.yaml", "config/test/config.yaml"])
def test_shipped_configs_are_valid(path):
    cfg = config.load(ROOT / path)
    assert all(isinstance(d, str) for d in cfg["datasets"])


def test_invalid_value_names_the_field(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text(yaml.safe_dump({"mcrt": {"n_rays": 0}}))
    with pytest.raises(config.ConfigError, match=r"mcrt/n_rays"):
        config.load(p)


def test_unknown_key_is_rejected(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("mcrtt: {}\n")
    with pytest.raises(config.ConfigError, match="mcrtt"):
        config.load(p)


def test_workflow_schema_is_the_package_schema():
    assert (ROOT / "workflow/schemas/config.schema.yaml").resolve() == config.SCHEMA_PATH.resolve()
