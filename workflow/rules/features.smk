# First-echo waveform features (docs/method.md §(h)) of real and simulated pulses: one code path.


rule features_real:
    input:
        config=stage_config("features_real", "features"),
        pulses=result("select", "{dataset}.parquet"),
        calibration=result("calibration", "{dataset}.json"),
    output:
        result("features", "{dataset}_real.parquet"),
    log:
        result("logs", "features", "{dataset}_real.log"),
    benchmark:
        result("benchmarks", "features", "{dataset}_real.tsv")
    conda:
        ENV
    threads: 1
    shell:
        "waveforest features {input.pulses} --calibration {input.calibration} "
        "--out {output} --config {input.config} > {log} 2>&1"


rule features_sim:
    input:
        config=stage_config("features_sim", "features"),
        pulses=expand(result("simulate", "{{dataset}}", "{chunk}.parquet"), chunk=CHUNKS),
        calibration=result("calibration", "{dataset}.json"),
    output:
        result("features", "{dataset}_sim.parquet"),
    log:
        result("logs", "features", "{dataset}_sim.log"),
    benchmark:
        result("benchmarks", "features", "{dataset}_sim.tsv")
    conda:
        ENV
    threads: 1
    shell:
        "waveforest features {input.pulses} --calibration {input.calibration} "
        "--out {output} --config {input.config} > {log} 2>&1"
