# The self-contained HTML report.


rule report:
    input:
        unpack(report_inputs),
    output:
        html="results/report/index.html",
    log:
        "results/logs/report.log",
    benchmark:
        "results/benchmarks/report.tsv"
    conda:
        "../envs/pipeline.yaml"
    threads: 1
    resources:
        mem_mb=1500,
    params:
        skipped=skipped_stages,
    script:
        "../scripts/report.py"
