# The self-contained HTML report.


rule report:
    input:
        unpack(report_inputs),
    output:
        html="results/report/index.html",
    params:
        lenses=LENSES,
        skipped=skipped_stages,
        error_history="results/diagnostics/error_history.csv",
    conda:
        "../envs/pipeline.yaml"
    log:
        "results/logs/report.log",
    benchmark:
        "results/benchmarks/report.tsv"
    script:
        "../scripts/report.py"
