# waveforest: the study of Hovi & Korpela (2014) as a workflow.
# Every rule calls one `waveforest` subcommand; see README.md and workflow/rules/.
from snakemake.utils import min_version

min_version("8.0")


configfile: "config/config.yaml"


include: "workflow/rules/executor.smk"
include: "workflow/rules/common.smk"
include: "workflow/rules/config.smk"
include: "workflow/rules/campaign.smk"
include: "workflow/rules/ingest.smk"
include: "workflow/rules/calibrate.smk"
include: "workflow/rules/select.smk"
include: "workflow/rules/simulate.smk"
include: "workflow/rules/features.smk"
include: "workflow/rules/analyses.smk"
include: "workflow/rules/diagnose.smk"
include: "workflow/rules/report.smk"
include: "workflow/rules/survey.smk"


rule all:
    input:
        "results/report/report.html",
    default_target: True
