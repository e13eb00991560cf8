# LAS waveform packets -> pulse table.


rule ingest:
    input:
        config=stage_config("ingest"),
        las=las_file,
        trajectory=trajectory_file,
    output:
        result("pulses", "{dataset}.parquet"),
    log:
        result("logs", "ingest", "{dataset}.log"),
    benchmark:
        result("benchmarks", "ingest", "{dataset}.tsv")
    conda:
        ENV
    threads: 1
    shell:
        "waveforest ingest {input.las} --out {output} --dataset {wildcards.dataset} "
        "--trajectory {input.trajectory} --config {input.config} > {log} 2>&1"
