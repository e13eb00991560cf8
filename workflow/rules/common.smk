# Shared definitions: config validation, the campaign folder, datasets, helpers.
import os
import sys

import yaml
from snakemake.utils import validate

from waveforest import config as waveforest_config
from waveforest.config_keys import stage_keys
from waveforest.errors import WaveforestError
from waveforest.io.tables import read_datasets


SCHEMA = "../schemas/config.schema.yaml"


def _schema_types(schema):
    """The JSON types a (sub)schema allows; empty when it names none."""
    t = schema.get("type", [])
    return {t} if isinstance(t, str) else set(t)


def _typed_overrides(values, overrides, schema, path=()):
    """Give the ``--config`` values their schema types, in place.

    Snakemake reads ``--config KEY=VALUE`` values with YAML's BaseLoader, so every scalar of a
    nested value arrives as a string ('campaign={"effects": {"understory": 1.5}}' gives
    ``"1.5"``), and a value it cannot parse arrives as the whole string. Each string whose schema
    does not allow a string is parsed as YAML (JSON is YAML); one that does not parse is an error
    naming the key. Only keys given on the command line are touched.
    """
    for key, value in overrides.items():
        here = path + (key,)
        props = schema.get("properties", {})
        sub = props[key] if key in props else schema.get("additionalProperties")
        if not isinstance(sub, dict):
            continue  # an unknown key: validation reports it
        types = _schema_types(sub)
        if types == {"string"} and isinstance(value, (int, float)) and not isinstance(value, bool):
            raise ValueError(
                f"--config {'.'.join(here)}={value!r}: expected text, and Snakemake read a number "
                "(it reads 2010_12_1 as 2010121, quoted or not); set this key in a --configfile"
            )
        if isinstance(value, str) and types and "string" not in types:
            try:
                values[key] = yaml.safe_load(value)
            except yaml.YAMLError as exc:
                raise ValueError(
                    f"--config {'.'.join(here)}={value!r}: not valid YAML/JSON for a value of type "
                    f"{' or '.join(sorted(types))} ({exc})"
                ) from None
        elif isinstance(value, dict) and isinstance(values.get(key), dict):
            _typed_overrides(values[key], value, sub, here)
        elif isinstance(value, list) and isinstance(sub.get("items"), dict):
            item_types = _schema_types(sub["items"])
            if item_types and "string" not in item_types:
                values[key] = [yaml.safe_load(v) if isinstance(v, str) else v for v in value]


with open(os.path.join(workflow.current_basedir, SCHEMA)) as _fh:
    _typed_overrides(config, dict(workflow.config_settings.config), yaml.safe_load(_fh))
# A bad config ends in one line naming the key path and what was expected (the CLI's check),
# not in Snakemake's dump of the schema.
_sources = [str(f) for f in (getattr(workflow.config_settings, "configfiles", None) or [])]
try:
    waveforest_config.validate(config, source=", ".join(_sources) or "config",
                               overrides=dict(workflow.config_settings.config))
except waveforest_config.ConfigError as _exc:
    sys.exit(f"waveforest: error: {_exc}")
validate(config, schema=SCHEMA)

STUDY_CONFIG = ", ".join(_sources or ["config/config.yaml"]) + (
    " with --config overrides" if workflow.config_settings.config else "")
"""The config the study ran with, as the report names it."""

RESULTS = "results"
CAMPAIGN = config["data"] if config["data"] else os.path.join(RESULTS, "campaign")
DATASETS = config["datasets"]
COMPARE_DATASETS = [d for d in config["simulate"]["datasets"] if d in DATASETS]
CHUNKS = list(range(config["simulate"]["chunks"]))
REFERENCE_DATASET = config["reference_dataset"]

# The CLI of every stage reads the validated config (defaults filled) from a file that rule
# `config` writes when the workflow runs, one per stage: results/config/<stage>.yaml. The config
# keys a stage depends on are derived from its source (waveforest.config_keys: every read of
# `cfg` in the stage module and in the settings builders it calls); its file is rewritten, and
# the stage rerun, only when those keys change (they are the `config` job's params), so a config
# change reruns exactly the steps that depend on it, and planning (-n, --lint) writes nothing.
STAGE_KEYS = {}


def stage_config(stage, module=None):
    """The config file of ``stage``, whose keys are those its module (default: the stage's name)
    reads; a stage that reads the whole config depends on every key."""
    keys = stage_keys("waveforest.stages.{}".format(module or stage))
    STAGE_KEYS[stage] = tuple(sorted(config)) if "*" in keys else keys
    return result("config", "{}.yaml".format(stage))


def config_values(wildcards):
    """The config values that the stage of a `config` job depends on, by key."""
    out = {}
    for key in STAGE_KEYS[wildcards.stage]:
        node = config
        for part in key.split("/"):
            node = node[part]
        out[key] = node
    return out


VALIDATED_CONFIG = os.path.join(RESULTS, "config", ".validated.yaml")
"""The whole validated config (defaults filled) of this run, written when it starts; rule
`config` copies it for each stage."""


onstart:
    os.makedirs(os.path.dirname(VALIDATED_CONFIG), exist_ok=True)
    _part = "{}.part".format(VALIDATED_CONFIG)
    with open(_part, "w") as fh:
        fh.write(yaml.safe_dump(config, sort_keys=True))
    os.replace(_part, VALIDATED_CONFIG)


def _user_datasets():
    """Rows of the user's datasets.csv by dataset name (real data only), checked by the one
    reader of the table; a bad table stops the workflow with one line."""
    path = os.path.join(CAMPAIGN, "datasets.csv")
    try:
        table = read_datasets(path)
    except WaveforestError as exc:
        sys.exit(f"waveforest: error: {exc} (config key 'data' names the campaign folder)")
    rows = {str(row["dataset"]): row for row in table.to_dict("records")}
    missing = [d for d in DATASETS if d not in rows]
    if missing:
        sys.exit(f"waveforest: error: {path}: dataset(s) {', '.join(missing)} of the config are not listed")
    for column in ("las_file", "trajectory_file"):
        if column not in table.columns:
            sys.exit(f"waveforest: error: {path}: no column {column} (the dataset's file in the campaign folder)")
    return rows


USER_DATASETS = _user_datasets() if config["data"] else {}


def campaign_file(name):
    """A file of the campaign folder (datasets.csv, fields.csv, targets.csv)."""
    return os.path.join(CAMPAIGN, name)


def las_file(wildcards):
    """The LAS waveform file of a dataset."""
    if config["data"]:
        return os.path.join(CAMPAIGN, USER_DATASETS[wildcards.dataset]["las_file"])
    return os.path.join(CAMPAIGN, "{}.las".format(wildcards.dataset))


def trajectory_file(wildcards):
    """The sensor trajectory CSV of a dataset."""
    if config["data"]:
        return os.path.join(CAMPAIGN, USER_DATASETS[wildcards.dataset]["trajectory_file"])
    return os.path.join(CAMPAIGN, "{}_trajectory.csv".format(wildcards.dataset))


def result(*parts):
    """A path under the results folder."""
    return os.path.join(RESULTS, *parts)


def output_dir(wildcards, output):
    """Folder of a rule's first output."""
    return os.path.dirname(output[0])


def results_dir(wildcards, output):
    """The results folder, two levels above a rule's first output."""
    return os.path.dirname(os.path.dirname(output[0]))


ENV = "../envs/waveforest.yaml"



def reference_system(wildcards):
    """S(t) of config reference_dataset if it is processed, else nothing (a Gaussian is used)."""
    if REFERENCE_DATASET in DATASETS:
        return result("calibration", "{}.parquet".format(REFERENCE_DATASET))
    return []


def system_option(wildcards, input):
    """The --system option of the studies, empty when the reference S(t) is not available."""
    return "--system {}".format(input.system) if input.system else ""

