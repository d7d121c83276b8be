# The default dataset is simulated when its configured folder does not exist (or with
# --config simulate=true). The rule is defined only then, so a user's dataset is never touched.

if SIMULATE:

    checkpoint simulate_dataset:
        output:
            dataset=directory(config["dataset"]),
        log:
            "results/logs/simulate_dataset.log",
        benchmark:
            "results/benchmarks/simulate_dataset.tsv"
        conda:
            "../envs/pipeline.yaml"
        threads: 1
        resources:
            mem_mb=1500,
        params:
            simulation=config["simulate_if_missing"],
        script:
            "../scripts/simulate_dataset.py"
