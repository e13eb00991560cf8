# The validated config each stage's CLI reads (--config): results/config/<stage>.yaml, written
# when the workflow runs (never while planning), and rewritten only when the keys the stage
# declares with stage_config (common.smk) change: they are this job's params.

rule config:
    output:
        result("config", "{stage}.yaml"),
    params:
        values=config_values,
        validated=VALIDATED_CONFIG,
    log:
        result("logs", "config", "{stage}.log"),
    localrule: True
    conda:
        ENV
    # a shell job: Snakemake runs a `run:` job in a new Snakemake process (seconds each)
    shell:
        "cp {params.validated} {output} 2> {log}"
