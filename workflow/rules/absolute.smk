# Absolute spectral radiance (Section 2.6, Eq. 9, Table 1): R^-1 per band with its budget.
# One job per lens: the two lenses of the camera are independent sensors.


rule absolute:
    input:
        unpack(stage_inputs("absolute")),
    output:
        artefact="results/absolute/{lens}.nc",
    log:
        "results/logs/absolute/{lens}.log",
    benchmark:
        "results/benchmarks/absolute/{lens}.tsv"
    conda:
        "../envs/pipeline.yaml"
    threads: 1
    resources:
        mem_mb=job_memory_mb("absolute"),
    params:
        dataset=config["dataset"],
        config=stage_params(config, "absolute"),
        dataset_subset=dataset_subset("absolute"),
        # the package code the job runs: editing it reruns the stage and what depends on it
        code=stage_code_sha256("absolute"),
    script:
        "../scripts/absolute.py"
