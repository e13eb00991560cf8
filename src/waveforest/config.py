"""Study configuration: load a YAML file, validate it and fill in defaults.

The JSON schema ``config.schema.yaml`` (also ``workflow/schemas/``) is the one source of
every default; Snakemake's ``validate`` and the CLI use the same file. The schema is closed:
every object lists its keys (``additionalProperties: false``) or, for a genuine map such as
``campaign.effects``, the schema of its values and the names it accepts, so a misspelled key
at any depth is an error that names its path.

Beyond the schema, :func:`validate` checks the names that live in package resources: every
species slug (``simulate.species``, ``campaign.species``, the species keys of
``simulate.height_range_m`` ...) must be one of Table 1's species (``resources/vegetation``)
and every ``classify.groups`` entry one of the four functional groups.
"""

from __future__ import annotations

import copy
import functools
import re
from pathlib import Path
from typing import Any

import jsonschema
import yaml

from waveforest.constants import FUNCTIONAL_GROUPS
from waveforest.errors import WaveforestError
from waveforest.species import species_slugs

SCHEMA_PATH = Path(__file__).with_name("config.schema.yaml")


class YamlLoader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):
    """libyaml's safe loader where PyYAML was built with it, with YAML 1.2's numbers: digits
    joined by underscores, as in the dataset name 2012_10_1, stay a string (YAML 1.1 reads the
    number 2012101)."""


YamlLoader.yaml_implicit_resolvers = {
    first: [(tag, rx) for tag, rx in resolvers if tag not in ("tag:yaml.org,2002:int", "tag:yaml.org,2002:float")]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()}
for _tag, _rx, _first in (
        ("tag:yaml.org,2002:int", r"^(?:[-+]?[0-9]+|0x[0-9a-fA-F]+)$", "-+0123456789"),
        ("tag:yaml.org,2002:float", r"^(?:[-+]?(?:[0-9]+\.[0-9]*|\.[0-9]+)(?:[eE][-+]?[0-9]+)?"
                                    r"|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$", "-+0123456789.")):
    YamlLoader.add_implicit_resolver(_tag, re.compile(_rx), list(_first))


SPECIES_LISTS = (("campaign", "species"), ("simulate", "species"), ("classify", "three_species"))
"""Config keys holding lists of species slugs (null allowed where the schema allows it)."""

SPECIES_MAPS = (("simulate", "height_range_m"), ("simulate", "compare_min_h_m"),
                ("sensor_study", "heights_m"), ("sensor_study", "min_echo_h_m"))
"""Config keys holding maps species slug -> value."""


class ConfigError(WaveforestError):
    """An invalid configuration."""


COMMAND_LINE = "--config on the command line"
"""Where an error in a key given with Snakemake's ``--config KEY=VALUE`` is said to come from."""


@functools.cache
def _schema_cached() -> dict:
    with open(SCHEMA_PATH) as fh:
        return yaml.load(fh, Loader=YamlLoader)


def schema() -> dict:
    """The config JSON schema (a fresh copy: callers may modify it)."""
    return copy.deepcopy(_schema_cached())


def fill_defaults(sub_schema: dict, instance: Any) -> None:
    """Fill the schema's defaults into ``instance`` in place, at every depth.

    A key absent from a mapping gets a copy of its ``default``; then every present key whose
    schema has ``properties`` is filled in turn (so a section defaulted to ``{}`` gets its own
    keys' defaults, however deep). Values of the wrong type are left for validation to report.
    """
    if not isinstance(instance, dict):
        return
    for name, prop in sub_schema.get("properties", {}).items():
        if name not in instance and "default" in prop:
            instance[name] = copy.deepcopy(prop["default"])
        if name in instance:
            fill_defaults(prop, instance[name])


def _message(exc: jsonschema.ValidationError) -> tuple[list[str], str]:
    """The key path of one schema violation and ``path: what was expected``."""
    parts = [str(p) for p in exc.absolute_path]
    if exc.validator == "additionalProperties" and exc.validator_value is False and isinstance(exc.instance, dict):
        known = list(exc.schema.get("properties", {}))
        extra = [k for k in exc.instance if k not in known]
        parts = parts + [str(extra[0])]
        return parts, f"{'/'.join(parts)}: unknown key; expected one of {', '.join(known)}"
    if "propertyNames" in exc.relative_schema_path and exc.validator == "enum":
        parts = parts + [str(exc.instance)]
        return parts, f"{'/'.join(parts)}: unknown name; expected one of {', '.join(map(str, exc.validator_value))}"
    hint = ""
    if exc.validator == "type" and "string" in str(exc.validator_value) and isinstance(exc.instance, int):
        hint = " (YAML 1.1 reads digits joined by underscores, such as 2012_10_1, as a number: quote the name)"
    return parts, f"{'/'.join(parts) or '(top level)'}: {exc.message}{hint}"


def _given(parts: list[str], overrides: dict | None) -> bool:
    """Whether the key path ``parts`` (or a parent of it) was set in ``overrides``."""
    here = overrides
    for part in parts:
        if not isinstance(here, dict) or part not in here:
            return False
        here = here[part]
        if not isinstance(here, dict):
            return True
    return bool(parts)


def _fill_all(sub_schema: dict, instance: Any) -> None:
    """:func:`fill_defaults`, also into the items of arrays and the values of maps."""
    fill_defaults(sub_schema, instance)
    if isinstance(instance, dict):
        for name, value in instance.items():
            prop = sub_schema.get("properties", {}).get(name)
            if prop is None and isinstance(sub_schema.get("additionalProperties"), dict):
                prop = sub_schema["additionalProperties"]
            if prop is not None:
                _fill_all(prop, value)
    elif isinstance(instance, list) and isinstance(sub_schema.get("items"), dict):
        for value in instance:
            _fill_all(sub_schema["items"], value)


def validate_document(sch: dict, document: dict, source: str, error: type[Exception] = ConfigError) -> dict:
    """Fill ``sch``'s defaults into ``document`` in place (also into array items and map values)
    and validate it as :func:`validate` does the config (the closed schema of another YAML
    file, e.g. a survey's).

    Raises ``error`` ``source: key/path: what was expected`` for the first violation.
    """
    _fill_all(sch, document)
    found = jsonschema.exceptions.best_match(jsonschema.Draft202012Validator(sch).iter_errors(document))
    if found is not None:
        raise error(f"{source}: {_message(found)[1]}")
    return document


def _check_names(config: dict, source: str, overrides: dict | None) -> None:
    """Species slugs and functional groups of the config are known ones."""
    known = species_slugs()

    def check(values, path: str, allowed, what: str) -> None:
        for v in values:
            if v not in allowed:
                where = COMMAND_LINE if _given(path.split("/"), overrides) else source
                raise ConfigError(f"{where}: {path}: unknown {what} {v!r}; expected one of {', '.join(allowed)}")

    for section, key in SPECIES_LISTS:
        check(config[section][key] or (), f"{section}/{key}", known, "species")
    for section, key in SPECIES_MAPS:
        check(config[section][key], f"{section}/{key}", known, "species")
    check([config["classify"]["normaliser"]], "classify/normaliser", known, "species")
    check(config["classify"]["groups"], "classify/groups", FUNCTIONAL_GROUPS, "functional group")


def validate(config: dict, source: str = "<config>", overrides: dict | None = None) -> dict:
    """Fill defaults into ``config`` in place, validate it, and return it.

    Parameters
    ----------
    config : mapping of a (possibly partial) config; keys absent get the schema's defaults.
    source : name of the config in error messages (a file name).
    overrides : the part of ``config`` given on the command line (Snakemake's ``--config``);
        an error in a key it sets is blamed on :data:`COMMAND_LINE`, not on ``source``.

    Raises
    ------
    ConfigError
        ``source: key/path: what was expected`` for the first violation (unknown keys at any
        depth, wrong types or ranges, unknown effect, species or group names).
    """
    sch = _schema_cached()
    fill_defaults(sch, config)
    error = jsonschema.exceptions.best_match(jsonschema.Draft202012Validator(sch).iter_errors(config))
    if error is not None:
        parts, text = _message(error)
        raise ConfigError(f"{COMMAND_LINE if _given(parts, overrides) else source}: {text}")
    _check_names(config, source, overrides)
    _check_diagnosed(config, source, overrides)
    return config


def _check_diagnosed(config: dict, source: str, overrides: dict | None) -> None:
    """``diagnose.datasets`` names comparison datasets that are processed (``simulate.datasets``
    within ``datasets``), at least one, and ``diagnose.ring_m`` lies beyond ``select.tree_radius_m``:
    checked here, not after the upstream stages have run."""
    ring, radius = config["diagnose"]["ring_m"], config["select"]["tree_radius_m"]
    if ring is not None and ring <= radius:
        where = COMMAND_LINE if _given(["diagnose", "ring_m"], overrides) else source
        raise ConfigError(f"{where}: diagnose/ring_m: {ring} is not beyond select/tree_radius_m ({radius} m); "
                          "expected a larger radius, or null for no rings")
    chosen = config["diagnose"]["datasets"]
    if chosen is None:
        return
    compared = [d for d in config["simulate"]["datasets"] if d in config["datasets"]]
    where = COMMAND_LINE if _given(["diagnose", "datasets"], overrides) else source
    if not chosen:
        raise ConfigError(f"{where}: diagnose/datasets: expected at least one dataset (null: every comparison "
                          f"dataset, {', '.join(compared)})")
    for d in chosen:
        if d not in compared:
            raise ConfigError(f"{where}: diagnose/datasets: {d!r} is not a comparison dataset that is processed; "
                              f"expected one of {', '.join(compared) or '(none: simulate.datasets within datasets)'}")


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
                config = yaml.load(fh, Loader=YamlLoader) or {}
            except yaml.YAMLError as exc:
                raise ConfigError(f"{path}: not valid YAML ({exc})") from None
        if not isinstance(config, dict):
            raise ConfigError(f"{path}: expected a mapping at the top level")
    for key, value in (overrides or {}).items():
        config[key] = value
    return validate(config, source)


def changes(config: dict, default: dict | None = None, path: str = "") -> list[tuple[str, Any, Any]]:
    """(dotted key path, default, value) of every leaf of ``config`` that differs from ``default``
    (None: the schema's defaults, :func:`load` of no file), in key order."""
    default = load(None) if default is None and not path else default
    if isinstance(config, dict) and isinstance(default, dict):
        out = []
        for k in sorted(set(config) | set(default), key=str):
            out += changes(config.get(k), default.get(k), f"{path}.{k}" if path else str(k))
        return out
    return [] if config == default else [(path, default, config)]
