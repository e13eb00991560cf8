"""Config schema: defaults, validation messages, and agreement with the shipped configs."""

from pathlib import Path

import pytest
import yaml

from waveforest import config

ROOT = Path(__file__).resolve().parents[1]


def test_empty_config_gets_every_default():
    cfg = config.load()
    # Sobol' + roulette at 16384 rays: the sigma(t) error of 30,000 random rays (docs/validation.md)
    assert (cfg["mcrt"]["n_rays"], cfg["mcrt"]["sampler"], cfg["mcrt"]["roulette"]) == (16384, "sobol", 0.5)
    assert cfg["campaign"]["samples_per_species"] is None  # Table 1's design counts
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


def test_dataset_names_need_no_quotes(tmp_path):
    """YAML 1.1 reads 2012_10_1 as the number 2012101; the config reads it as the name, and keeps
    numbers numbers. Where another loader made it a number (Snakemake's), the message says why."""
    p = tmp_path / "c.yaml"
    p.write_text("datasets: [2010_12_1, 2012_10_1]\nseed: 7\nmcrt: {n_rays: 1024, roulette: 0.25}\n")
    cfg = config.load(p)
    assert cfg["datasets"] == ["2010_12_1", "2012_10_1"] and cfg["seed"] == 7 and cfg["mcrt"]["roulette"] == 0.25
    with pytest.raises(config.ConfigError, match=r"datasets/0: 2010121 is not of type 'string' \(YAML 1.1 reads"):
        config.validate({"datasets": [2010121]}, "config.yaml")


def test_unknown_key_is_rejected(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("mcrtt: {}\n")
    with pytest.raises(config.ConfigError, match="mcrtt"):
        config.load(p)


def test_workflow_schema_is_the_package_schema():
    assert (ROOT / "workflow/schemas/config.schema.yaml").resolve() == config.SCHEMA_PATH.resolve()


def _object_nodes(node, path=()):
    """(path, node) of every object schema in the config schema, at every depth."""
    if isinstance(node, dict):
        types = node.get("type") if isinstance(node.get("type"), list) else [node.get("type")]
        if "object" in types or "properties" in node:
            yield path, node
        for key, sub in node.items():
            yield from _object_nodes(sub, path + (key,))
    elif isinstance(node, list):
        for i, sub in enumerate(node):
            yield from _object_nodes(sub, path + (i,))


def test_every_schema_object_is_closed_and_described():
    nodes = list(_object_nodes(config.schema()))
    assert len(nodes) > 20  # the walk reaches nested sections (sensor/cfd, sensitivity/reference_system, ...)
    for path, node in nodes:
        extra = node.get("additionalProperties")
        assert extra is False or isinstance(extra, dict), f"{'/'.join(map(str, path))}: additionalProperties"
        assert node.get("description"), f"{'/'.join(map(str, path))}: no description"


@pytest.mark.parametrize("cfg, where", [
    ({"mcrt": {"n_rayz": 5}}, "mcrt/n_rayz: unknown key; expected one of n_rays"),
    ({"sensor": {"cfd": {"fractoin": 0.4}}}, "sensor/cfd/fractoin: unknown key"),
    ({"sensitivity": {"reference_system": {"fwhm": 3}}}, "sensitivity/reference_system/fwhm: unknown key"),
    ({"campaign": {"effects": {"understorey": 1.5}}}, "campaign/effects/understorey: unknown name; expected one of"),
    ({"simulate": {"effects": {"hotspot": "x"}}}, "simulate/effects/hotspot"),
    ({"simulate": {"species": ["oak"]}}, "simulate/species: unknown species 'oak'; expected one of scots_pine"),
    ({"simulate": {"height_range_m": {"brich": [1, 2]}}}, "simulate/height_range_m: unknown species 'brich'"),
    ({"classify": {"groups": ["conifer", "trees"]}}, "classify/groups: unknown functional group 'trees'"),
    ({"diagnose": {"datasets": []}}, "diagnose/datasets: expected at least one dataset"),
    ({"diagnose": {"datasets": ["2010_12_1", "2099_01_1"]}},
     "diagnose/datasets: '2099_01_1' is not a comparison dataset that is processed; expected one of 2010_12_1, "),
    ({"datasets": ["2010_12_1"], "diagnose": {"datasets": ["2012_10_1"]}},
     "diagnose/datasets: '2012_10_1' is not a comparison dataset that is processed; expected one of 2010_12_1"),
])
def test_misspelled_nested_keys_and_names(tmp_path, cfg, where):
    p = tmp_path / "c.yaml"
    p.write_text(yaml.safe_dump(cfg))
    with pytest.raises(config.ConfigError) as exc:
        config.load(p)
    assert str(exc.value).startswith(f"{p}: {where}"), str(exc.value)


def test_effect_names_are_the_catalogue():
    from waveforest.effects import CATALOGUE

    assert config.schema()["$defs"]["effect_name"]["enum"] == list(CATALOGUE)


def test_defaults_are_filled_at_every_depth():
    cfg = config.validate({"sensitivity": {"pulses": 3}, "sensor": {"cfd": {}}})
    assert cfg["sensitivity"]["pulses"] == 3
    assert cfg["sensitivity"]["reference_system"]["fwhm_ns"] == pytest.approx(7.2)
    assert cfg["sensor"]["cfd"]["fraction"] == pytest.approx(0.5)
    assert cfg["sensor"]["features"]["segment_sd"] == pytest.approx(3.0)
    assert cfg["calibrate"]["cos_incidence"] is True  # the schema's default, which the code now uses
    assert cfg["reference_dataset"] == "2010_12_1"
    # defaults are copies: filling one config does not change the next one's
    cfg["campaign"]["effects"]["understory"] = 1.0
    assert config.validate({})["campaign"]["effects"] == {}


def _schema_keys(node, keys=None):
    keys = set() if keys is None else keys
    if isinstance(node, dict):
        keys.update(node.get("properties", {}))
        for sub in node.values():
            _schema_keys(sub, keys)
    return keys


OWN_PACKAGES = ["sensor", "analysis", "campaign", "diagnose", "mcrt", "vegetation"]


def test_code_repeats_no_schema_default():
    """No ``x.get("key", <literal>)`` on a config key: a default in the code would differ from the
    schema's one day (calibrate.cos_incidence was True in the schema and False in the code)."""
    import ast

    keys = _schema_keys(config.schema())
    src = Path(config.__file__).parent
    files = [p for pkg in OWN_PACKAGES for p in (src / pkg).rglob("*.py")] + [src / "cliutil.py"]
    found = []
    for path in files:
        for node in ast.walk(ast.parse(path.read_text())):
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "get"
                    and len(node.args) == 2 and isinstance(node.args[0], ast.Constant)
                    and node.args[0].value in keys
                    and isinstance(node.args[1], (ast.Constant, ast.Tuple, ast.List, ast.Dict, ast.Name))):
                found.append(f"{path.relative_to(src)}:{node.lineno}: .get({node.args[0].value!r}, ...)")
    assert not found, "\n".join(found)


def test_seed_override_is_validated():
    with pytest.raises(config.ConfigError, match="seed"):
        config.load(overrides={"seed": -1})
