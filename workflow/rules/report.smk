# The self-contained HTML report, and each of its figures as a PNG for Snakemake's own report
# (snakemake --report results/snakemake-report.zip): one category per report section, the
# figure's number and caption as labels.


rule report:
    input:
        unpack(report_inputs),
    output:
        html="results/report/index.html",
        figures=report(
            directory("results/report/figures"),
            patterns=["{figure}.png"],
            caption="../report/figure.rst",
            category=report_figure_category,
            labels=report_figure_labels,
        ),
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
        dataset=report_dataset,
        settings=report_settings,
    script:
        "../scripts/report.py"
