# Fly your own survey (docs/survey.md), split into jobs: `snakemake results/survey/NAME/summary.json`
# flies surveys/NAME/SCENE.yaml + surveys/NAME/SURVEY.yaml. SURVEY_PARTS jobs (environment
# variable WAVEFOREST_SURVEY_PARTS, default 4) each trace the tiles k with k mod N = I into the
# survey's cache beside the output folder; one job merges them into the LAS files. Not part of
# `rule all`. On SLURM: the existing profile (workflow/profiles/), one part per job.
import os

from waveforest.survey.scene import input_files

SURVEY_PARTS = int(os.environ.get("WAVEFOREST_SURVEY_PARTS", "4"))


rule survey_part:
    input:
        config=stage_config("survey"),
        scene="surveys/{name}/SCENE.yaml",
        survey="surveys/{name}/SURVEY.yaml",
        files=lambda wildcards: input_files(f"surveys/{wildcards.name}/SCENE.yaml",
                                            f"surveys/{wildcards.name}/SURVEY.yaml"),
    output:
        touch(result("survey", ".parts", "{name}", "{part}.done")),
    params:
        parts=SURVEY_PARTS,
        out=lambda wildcards: result("survey", wildcards.name),
    log:
        result("logs", "survey", "{name}_{part}.log"),
    conda:
        ENV
    threads: 2
    shell:
        "waveforest survey {input.scene} {input.survey} --out {params.out} --part {wildcards.part}/{params.parts} "
        "--no-progress --threads {threads} --config {input.config} > {log} 2>&1"


rule survey_merge:
    input:
        config=stage_config("survey"),
        scene="surveys/{name}/SCENE.yaml",
        survey="surveys/{name}/SURVEY.yaml",
        parts=lambda wildcards: expand(result("survey", ".parts", wildcards.name, "{part}.done"),
                                       part=range(SURVEY_PARTS)),
    output:
        result("survey", "{name}", "summary.json"),
    params:
        out=lambda wildcards: result("survey", wildcards.name),
    log:
        result("logs", "survey", "{name}_merge.log"),
    conda:
        ENV
    threads: 2
    shell:
        "waveforest survey {input.scene} {input.survey} --out {params.out} --force "
        "--no-progress --threads {threads} --config {input.config} > {log} 2>&1"
