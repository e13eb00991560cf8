# First-echo waveform features (METHOD.md h) of real and simulated pulses: one code path.


rule features_real:
    input:
        pulses=result("select", "{dataset}.parquet"),
        calibration=result("calibration", "{dataset}.json"),
    output:
        result("features", "{dataset}_real.parquet"),
    params:
        features=config["sensor"]["features"],
        config=CONFIG_FILE,
    log:
        result("logs", "features", "{dataset}_real.log"),
    benchmark:
        result("benchmarks", "features", "{dataset}_real.tsv")
    conda:
        ENV
    threads: 1
    shell:
        "waveforest features {input.pulses} --calibration {input.calibration} "
        "--out {output} --config {params.config} > {log} 2>&1"


rule features_sim:
    input:
        pulses=expand(result("simulate", "{{dataset}}", "{chunk}.parquet"), chunk=CHUNKS),
        calibration=result("calibration", "{dataset}.json"),
    output:
        result("features", "{dataset}_sim.parquet"),
    params:
        features=config["sensor"]["features"],
        config=CONFIG_FILE,
    log:
        result("logs", "features", "{dataset}_sim.log"),
    benchmark:
        result("benchmarks", "features", "{dataset}_sim.tsv")
    conda:
        ENV
    threads: 1
    shell:
        "waveforest features {input.pulses} --calibration {input.calibration} "
        "--out {output} --config {params.config} > {log} 2>&1"
