# The self-contained HTML report.


rule report:
    input:
        unpack(report_inputs),
    output:
        html="results/report/index.html",
    params:
        lenses=report_lenses,
        skipped=skipped_stages,
    threads: 1
    resources:
        mem_mb=1500,
    conda:
        "../envs/pipeline.yaml"
    log:
        "results/logs/report.log",
    benchmark:
        "results/benchmarks/report.tsv"
    script:
        "../scripts/report.py"
