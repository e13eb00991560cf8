# Pulses that hit field samples (radius and echo rules, docs/method.md §(i1), i4).


rule select:
    input:
        config=stage_config("select"),
        pulses=result("agc", "{dataset}.parquet"),
        fields=campaign_file("fields.csv"),
        datasets=campaign_file("datasets.csv"),
    output:
        result("select", "{dataset}.parquet"),
    log:
        result("logs", "select", "{dataset}.log"),
    benchmark:
        result("benchmarks", "select", "{dataset}.tsv")
    conda:
        ENV
    threads: 1
    shell:
        "waveforest select {input.pulses} --fields {input.fields} --datasets {input.datasets} "
        "--out {output} --config {input.config} > {log} 2>&1"
