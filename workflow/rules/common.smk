# Shared definitions: config validation, the campaign folder, datasets, helpers.
import csv
import os

import yaml
from snakemake.utils import validate


validate(config, schema="../schemas/config.schema.yaml")

RESULTS = "results"
CAMPAIGN = config["data"] if config["data"] else os.path.join(RESULTS, "campaign")
DATASETS = config["datasets"]
COMPARE_DATASETS = [d for d in config["simulate"]["datasets"] if d in DATASETS]
CHUNKS = list(range(config["simulate"]["chunks"]))

# The CLI reads the same (validated, defaults filled) config the workflow sees. It is
# rewritten only when it changes; rules list the sections they use as params, so a change
# reruns exactly the steps that depend on it.
CONFIG_FILE = os.path.join(RESULTS, "config.yaml")
_text = yaml.safe_dump(config, sort_keys=True)
if not os.path.exists(CONFIG_FILE) or open(CONFIG_FILE).read() != _text:
    os.makedirs(RESULTS, exist_ok=True)
    with open(CONFIG_FILE, "w") as _fh:
        _fh.write(_text)


def _user_datasets():
    """Rows of the user's datasets.csv by dataset name (real data only)."""
    path = os.path.join(CAMPAIGN, "datasets.csv")
    if not os.path.exists(path):
        raise ValueError(f"{path}: no such file (config key 'data' names a campaign folder)")
    with open(path, newline="") as fh:
        rows = {row["dataset"]: row for row in csv.DictReader(fh)}
    missing = [d for d in DATASETS if d not in rows]
    if missing:
        raise ValueError(f"{path}: dataset(s) {', '.join(missing)} of the config are not listed")
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


def campaign_dir(wildcards, input):
    """The campaign folder, that of the rule's datasets.csv input."""
    return os.path.dirname(input.datasets)


ENV = "../envs/waveforest.yaml"


REFERENCE_DATASET = "2010_12_1"
"""The dataset whose S(t) the sensitivity and sensor studies use (METHOD.md i2, i3)."""


def reference_system(wildcards):
    """S(t) of the reference dataset if it is processed, else nothing (a Gaussian is used)."""
    if REFERENCE_DATASET in DATASETS:
        return result("calibration", "{}.parquet".format(REFERENCE_DATASET))
    return []


def system_option(wildcards, input):
    """The --system option of the studies, empty when the reference S(t) is not available."""
    return "--system {}".format(input.system) if input.system else ""
