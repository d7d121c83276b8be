# Dark frames (Section 2.8): bias, fixed pattern, dark current, hot pixels, read noise.
# One job per lens: the two lenses of the camera are independent sensors.


rule dark:
    input:
        unpack(stage_inputs("dark")),
    output:
        artefact="results/dark/{lens}.nc",
    log:
        "results/logs/dark/{lens}.log",
    benchmark:
        "results/benchmarks/dark/{lens}.tsv"
    conda:
        "../envs/pipeline.yaml"
    threads: 1
    resources:
        mem_mb=job_memory_mb("dark"),
    params:
        dataset=config["dataset"],
        config=stage_params(config, "dark"),
        dataset_subset=dataset_subset("dark"),
        # the package code the job runs: editing it reruns the stage and what depends on it
        code=stage_code_sha256("dark"),
    script:
        "../scripts/dark.py"
