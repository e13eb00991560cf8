# One HTML/Markdown report with every table and figure, the config and the versions.


rule report:
    input:
        config=stage_config("report"),
        table3=result("compare", "table3.csv"),
        sensitivity=result("sensitivity", "sensitivity.csv"),
        sensor_study=result("sensor_study", "sensor_study.csv"),
        classify=expand(result("classify", "{dataset}.json"), dataset=DATASETS),
        calibration=expand(result("calibration", "{dataset}.json"), dataset=DATASETS),
        diagnose=result("diagnose", "model.yaml"),
    output:
        html=result("report", "report.html"),
        markdown=result("report", "report.md"),
        table4=result("report", "table4.csv"),
        table4_md=result("report", "table4.md"),
    params:
        results=results_dir,
        study_config=STUDY_CONFIG,
    log:
        result("logs", "report.log"),
    benchmark:
        result("benchmarks", "report.tsv")
    conda:
        ENV
    threads: 1
    shell:
        "waveforest report {input.table3} {input.sensitivity} {input.sensor_study} {input.classify} "
        "{input.calibration} {input.diagnose} --results {params.results} --config {input.config} "
        "--study-config {params.study_config:q} --out {output.html} --markdown {output.markdown} > {log} 2>&1"
