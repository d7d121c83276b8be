# Closure and missing-effect diagnostics over every stage's residuals.


rule diagnostics:
    input:
        unpack(diagnostics_inputs),
    output:
        missing_effects="results/diagnostics/missing_effects.csv",
        unexplained="results/diagnostics/unexplained.csv",
        run_errors="results/diagnostics/run_errors.csv",
        # per experiment and level: residual chi-square against its dof, where structure sits
        residual_tests="results/diagnostics/residual_tests.csv",
        # per effect that may differ between the two sensors: one shared value against one per lens
        lens_tests="results/diagnostics/lens_tests.csv",
        # per band of the field match-up: the camera/reference scale against the lab calibration's prediction
        field_scale="results/diagnostics/field_scale.csv",
        # per fitted quantity with a physical range (window index, conversion gain, roll-off, dark current): value, range, verdict
        plausibility="results/diagnostics/plausibility.csv",
        # rebuilt at every run from the append-only ledger folder (one file per run, never rewritten)
        error_history="results/diagnostics/error_history.csv",
        # every measurement of every experiment: prediction, residual, expected noise, covariates
        closure="results/closure/residuals.nc",
    log:
        "results/logs/diagnostics.log",
    benchmark:
        "results/benchmarks/diagnostics.tsv"
    conda:
        "../envs/pipeline.yaml"
    threads: 1
    resources:
        mem_mb=1000,
    params:
        config=stage_params(config, "diagnostics"),
        ledger="results/diagnostics/ledger",
    script:
        "../scripts/diagnostics.py"
