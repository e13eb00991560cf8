"""Study configuration: load a YAML file, validate it and fill in defaults.

The JSON schema ``config.schema.yaml`` (also ``workflow/schemas/``) is the one source of
every default; Snakemake's ``validate`` and the CLI use the same file.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import jsonschema
import yaml

from .errors import WaveforestError

SCHEMA_PATH = Path(__file__).with_name("config.schema.yaml")


class ConfigError(WaveforestError):
    """An invalid configuration."""


def _schema() -> dict:
    with open(SCHEMA_PATH) as fh:
        return yaml.safe_load(fh)


def _with_defaults(validator_class):
    validate_props = validator_class.VALIDATORS["properties"]

    def set_defaults(validator, properties, instance, schema):
        if isinstance(instance, dict):
            for name, sub in properties.items():
                if "default" in sub and name not in instance:
                    instance[name] = yaml.safe_load(yaml.safe_dump(sub["default"]))
        yield from validate_props(validator, properties, instance, schema)

    return jsonschema.validators.extend(validator_class, {"properties": set_defaults})


_Validator = _with_defaults(jsonschema.Draft202012Validator)


def validate(config: dict, source: str = "<config>") -> dict:
    """Validate ``config`` in place, fill defaults, and return it."""
    try:
        # twice: defaults of nested objects created by the first pass are filled by the second
        _Validator(_schema()).validate(config)
        _Validator(_schema()).validate(config)
    except jsonschema.ValidationError as exc:
        where = "/".join(str(p) for p in exc.absolute_path) or "(top level)"
        raise ConfigError(f"{source}: {where}: {exc.message}") from None
    return config


def load(path: str | Path | None = None, overrides: dict | None = None) -> dict[str, Any]:
    """Read a YAML config (None = all defaults), apply ``overrides`` and validate."""
    config: dict = {}
    source = "<defaults>"
    if path is not None:
        path = Path(path)
        source = str(path)
        if not path.exists():
            raise ConfigError(f"{path}: no such config file")
        with open(path) as fh:
            try:
                config = yaml.safe_load(fh) or {}
            except yaml.YAMLError as exc:
                raise ConfigError(f"{path}: not valid YAML ({exc})") from None
        if not isinstance(config, dict):
            raise ConfigError(f"{path}: expected a mapping at the top level")
    for key, value in (overrides or {}).items():
        config[key] = value
    return validate(config, source)
