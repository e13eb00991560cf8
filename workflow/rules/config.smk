# The validated config each stage's CLI reads (--config): results/config/<stage>.yaml, written
# when the workflow runs (never while planning), and rewritten only when the keys the stage
# declares with stage_config (common.smk) change: they are this job's params.

rule config:
    output:
        result("config", "{stage}.yaml"),
    params:
        values=config_values,
    log:
        result("logs", "config", "{stage}.log"),
    localrule: True
    run:
        write_config(output[0])
