# Closure and missing-effect diagnostics over every stage's residuals.


rule diagnostics:
    input:
        unpack(diagnostics_inputs),
    output:
        missing_effects="results/diagnostics/missing_effects.csv",
        unexplained="results/diagnostics/unexplained.csv",
        run_errors="results/diagnostics/run_errors.csv",
    params:
        config=stage_params(config, "diagnostics"),
        # the ledger grows by one row per experiment and run; it is not an output,
        # so that a rerun appends to it instead of replacing it
        error_history="results/diagnostics/error_history.csv",
    conda:
        "../envs/pipeline.yaml"
    log:
        "results/logs/diagnostics.log",
    benchmark:
        "results/benchmarks/diagnostics.tsv"
    script:
        "../scripts/diagnostics.py"
