# The virtual ALS60 campaign, generated when the config names no real data.

if not config["data"]:

    rule synthesize:
        input:
            config=stage_config("synthesize"),
        output:
            datasets=result("campaign", "datasets.csv"),
            fields=result("campaign", "fields.csv"),
            targets=result("campaign", "targets.csv"),
            truth=result("campaign", "truth.json"),
            las=expand(result("campaign", "{dataset}.las"), dataset=DATASETS),
            trajectories=expand(result("campaign", "{dataset}_trajectory.csv"), dataset=DATASETS),
        params:
            out=output_dir,
        log:
            result("logs", "synthesize.log"),
        benchmark:
            result("benchmarks", "synthesize.tsv")
        conda:
            ENV
        threads: 2
        shell:
            "waveforest synthesize --config {input.config} --out {params.out} "
            "--threads {threads} > {log} 2>&1"
