# The paper's analyses: real vs simulated (Table 3, Figs. 6-7), sensitivity (Fig. 8),
# sensor study (Fig. 9) and real-data classification (Table 4).


rule compare:
    input:
        config=stage_config("compare"),
        real=expand(result("features", "{dataset}_real.parquet"), dataset=COMPARE_DATASETS),
        sim=expand(result("features", "{dataset}_sim.parquet"), dataset=COMPARE_DATASETS),
        selected=expand(result("select", "{dataset}.parquet"), dataset=COMPARE_DATASETS),
        simulated=expand(
            result("simulate", "{dataset}", "{chunk}.parquet"), dataset=COMPARE_DATASETS, chunk=CHUNKS
        ),
    output:
        table=result("compare", "table3.csv"),
        markdown=result("compare", "table3.md"),
        order=result("compare", "order_check.csv"),
        fig6=expand(result("compare", "fig6_{dataset}.png"), dataset=COMPARE_DATASETS),
        fig7=expand(result("compare", "fig7_{dataset}.png"), dataset=COMPARE_DATASETS),
    params:
        out=output_dir,
    log:
        result("logs", "compare.log"),
    benchmark:
        result("benchmarks", "compare.tsv")
    conda:
        ENV
    threads: 1
    shell:
        "waveforest compare --real {input.real} --sim {input.sim} "
        "--pulses-real {input.selected} --pulses-sim {input.simulated} "
        "--out {params.out} --config {input.config} > {log} 2>&1"


rule sensitivity:
    input:
        config=stage_config("sensitivity"),
        system=reference_system,
    output:
        table=result("sensitivity", "sensitivity.csv"),
        figure=result("sensitivity", "fig8.png"),
        baseline=result("sensitivity", "sensitivity_baseline.csv"),
        pulses=result("sensitivity", "sensitivity_pulses.parquet"),
    params:
        system=system_option,
        out=output_dir,
    log:
        result("logs", "sensitivity.log"),
    benchmark:
        result("benchmarks", "sensitivity.tsv")
    conda:
        ENV
    threads: 2
    shell:
        "waveforest sensitivity {params.system} --out {params.out} "
        "--threads {threads} --config {input.config} > {log} 2>&1"


rule sensor_study:
    input:
        config=stage_config("sensor_study"),
        system=reference_system,
    output:
        table=result("sensor_study", "sensor_study.csv"),
        figure=result("sensor_study", "fig9.png"),
        features=result("sensor_study", "sensor_study_features.csv"),
    params:
        system=system_option,
        out=output_dir,
    log:
        result("logs", "sensor_study.log"),
    benchmark:
        result("benchmarks", "sensor_study.tsv")
    conda:
        ENV
    threads: 2
    shell:
        "waveforest sensor-study {params.system} --out {params.out} "
        "--threads {threads} --config {input.config} > {log} 2>&1"


# Table 1's rule: a species with >= select.min_pulses single-echo pulses in at least one
# processed dataset enters every dataset's classification set, so each dataset's job reads the
# select tables of all datasets.
rule classify:
    input:
        config=stage_config("classify"),
        features=result("features", "{dataset}_real.parquet"),
        selected=expand(result("select", "{dataset}.parquet"), dataset=DATASETS),
    output:
        result("classify", "{dataset}.json"),
    log:
        result("logs", "classify", "{dataset}.log"),
    benchmark:
        result("benchmarks", "classify", "{dataset}.tsv")
    conda:
        ENV
    threads: 1
    shell:
        "waveforest classify {input.features} --select {input.selected} --out {output} "
        "--config {input.config} > {log} 2>&1"
