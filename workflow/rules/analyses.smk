# The paper's analyses: real vs simulated (Table 3, Figs. 6-7), sensitivity (Fig. 8),
# sensor study (Fig. 9) and real-data classification (Table 4).


rule compare:
    input:
        real=expand(result("features", "{dataset}_real.parquet"), dataset=COMPARE_DATASETS),
        sim=expand(result("features", "{dataset}_sim.parquet"), dataset=COMPARE_DATASETS),
        selected=expand(result("select", "{dataset}.parquet"), dataset=COMPARE_DATASETS),
        simulated=expand(
            result("simulate", "{dataset}", "{chunk}.parquet"), dataset=COMPARE_DATASETS, chunk=CHUNKS
        ),
    output:
        table=result("compare", "table3.csv"),
        markdown=result("compare", "table3.md"),
    params:
        out=output_dir,
        config=CONFIG_FILE,
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
        "--out {params.out} --config {params.config} > {log} 2>&1"


rule sensitivity:
    input:
        system=result("calibration", "2010_12_1.parquet") if "2010_12_1" in DATASETS else [],
    output:
        table=result("sensitivity", "sensitivity.csv"),
        figure=result("sensitivity", "fig8.png"),
    params:
        sensitivity=config["sensitivity"],
        mcrt=config["mcrt"],
        out=output_dir,
        config=CONFIG_FILE,
    log:
        result("logs", "sensitivity.log"),
    benchmark:
        result("benchmarks", "sensitivity.tsv")
    conda:
        ENV
    threads: 2
    shell:
        "waveforest sensitivity --system {input.system} --out {params.out} "
        "--threads {threads} --config {params.config} > {log} 2>&1"


rule sensor_study:
    input:
        system=result("calibration", "2010_12_1.parquet") if "2010_12_1" in DATASETS else [],
    output:
        table=result("sensor_study", "sensor_study.csv"),
        figure=result("sensor_study", "fig9.png"),
    params:
        sensor_study=config["sensor_study"],
        mcrt=config["mcrt"],
        out=output_dir,
        config=CONFIG_FILE,
    log:
        result("logs", "sensor_study.log"),
    benchmark:
        result("benchmarks", "sensor_study.tsv")
    conda:
        ENV
    threads: 2
    shell:
        "waveforest sensor-study --system {input.system} --out {params.out} "
        "--threads {threads} --config {params.config} > {log} 2>&1"


rule classify:
    input:
        features=result("features", "{dataset}_real.parquet"),
    output:
        result("classify", "{dataset}.json"),
    params:
        classify=config["classify"],
        config=CONFIG_FILE,
    log:
        result("logs", "classify", "{dataset}.log"),
    benchmark:
        result("benchmarks", "classify", "{dataset}.tsv")
    conda:
        ENV
    threads: 1
    shell:
        "waveforest classify {input.features} --out {output} --config {params.config} > {log} 2>&1"
