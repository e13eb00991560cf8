# AGC normalisation (Eq. 1) and system-waveform calibration (Eq. 8).


rule agc:
    input:
        config=stage_config("agc"),
        pulses=result("pulses", "{dataset}.parquet"),
        targets=campaign_file("targets.csv"),
        datasets=campaign_file("datasets.csv"),
    output:
        pulses=result("agc", "{dataset}.parquet"),
        fit=result("agc", "{dataset}.json"),
    log:
        result("logs", "agc", "{dataset}.log"),
    benchmark:
        result("benchmarks", "agc", "{dataset}.tsv")
    conda:
        ENV
    threads: 1
    shell:
        "waveforest agc {input.pulses} --targets {input.targets} --datasets {input.datasets} "
        "--out {output.pulses} --fit {output.fit} --config {input.config} > {log} 2>&1"


rule calibrate:
    input:
        config=stage_config("calibrate"),
        pulses=result("agc", "{dataset}.parquet"),
        targets=campaign_file("targets.csv"),
        datasets=campaign_file("datasets.csv"),
    output:
        system=result("calibration", "{dataset}.parquet"),
        json=result("calibration", "{dataset}.json"),
        plot=result("calibration", "{dataset}.png"),
    log:
        result("logs", "calibrate", "{dataset}.log"),
    benchmark:
        result("benchmarks", "calibrate", "{dataset}.tsv")
    conda:
        ENV
    threads: 1
    shell:
        "waveforest calibrate {input.pulses} --targets {input.targets} --datasets {input.datasets} "
        "--out {output.system} --json {output.json} --plot {output.plot} "
        "--config {input.config} > {log} 2>&1"
