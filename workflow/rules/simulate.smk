# MCRT + sensor simulation of the selected pulses of the modelled species, in chunks.


rule simulate:
    input:
        config=stage_config("simulate"),
        selected=result("select", "{dataset}.parquet"),
        fields=campaign_file("fields.csv"),
        datasets=campaign_file("datasets.csv"),
        system=result("calibration", "{dataset}.parquet"),
        calibration=result("calibration", "{dataset}.json"),
    output:
        result("simulate", "{dataset}", "{chunk}.parquet"),
    params:
        chunks=config["simulate"]["chunks"],
    log:
        result("logs", "simulate", "{dataset}_{chunk}.log"),
    benchmark:
        result("benchmarks", "simulate", "{dataset}_{chunk}.tsv")
    conda:
        ENV
    threads: 2
    shell:
        "waveforest simulate {input.selected} --fields {input.fields} --datasets {input.datasets} "
        "--system {input.system} --calibration {input.calibration} "
        "--chunk {wildcards.chunk} --chunks {params.chunks} --out {output} "
        "--threads {threads} --config {input.config} > {log} 2>&1"
