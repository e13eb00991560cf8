# Beyond the paper: find the disagreement, name the missing effect, add it, show the gap shrink.


rule diagnose:
    input:
        config=stage_config("diagnose"),
        selected=expand(result("select", "{dataset}.parquet"), dataset=COMPARE_DATASETS),
        real=expand(result("features", "{dataset}_real.parquet"), dataset=COMPARE_DATASETS),
        calibration=expand(result("calibration", "{dataset}.json"), dataset=COMPARE_DATASETS),
        system=expand(result("calibration", "{dataset}.parquet"), dataset=COMPARE_DATASETS),
        agc=expand(result("agc", "{dataset}.parquet"), dataset=COMPARE_DATASETS),
        datasets=campaign_file("datasets.csv"),
        targets=campaign_file("targets.csv"),
        fields=campaign_file("fields.csv"),
    output:
        model=result("diagnose", "model.yaml"),
        candidates=result("diagnose", "candidates.csv"),
        gap=result("diagnose", "gap_before_after.csv"),
        figure=result("diagnose", "gap.png"),
        signatures=result("diagnose", "signatures.csv"),
        limits=result("diagnose", "detection_limits.csv"),
        curve=result("diagnose", "detection_curve.csv"),
        power=result("diagnose", "power.png"),
        verdict=result("diagnose", "verdict.json"),
        summary=result("diagnose", "diagnose.md"),
    params:
        out=output_dir,
    log:
        result("logs", "diagnose.log"),
    benchmark:
        result("benchmarks", "diagnose.tsv")
    conda:
        ENV
    threads: 2
    shell:
        "waveforest diagnose --selected {input.selected} --features-real {input.real} "
        "--calibration {input.calibration} --system {input.system} --agc {input.agc} "
        "--datasets {input.datasets} --targets {input.targets} --fields {input.fields} "
        "--out {params.out} --threads {threads} --config {input.config} > {log} 2>&1"
