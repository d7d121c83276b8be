# Immersion factor (Section 2.7): log-linear extrapolation to 0-, Eq. (11), Eq. (10).
# One job per lens: the two lenses of the camera are independent sensors.


rule immersion:
    input:
        unpack(stage_inputs("immersion")),
    output:
        artefact="results/immersion/{lens}.nc",
    log:
        "results/logs/immersion/{lens}.log",
    benchmark:
        "results/benchmarks/immersion/{lens}.tsv"
    conda:
        "../envs/pipeline.yaml"
    threads: 1
    resources:
        mem_mb=job_memory_mb("immersion"),
    params:
        dataset=config["dataset"],
        config=stage_params(config, "immersion"),
        dataset_subset=dataset_subset("immersion"),
        # the package code the job runs: editing it reruns the stage and what depends on it
        code=stage_code_sha256("immersion"),
    script:
        "../scripts/immersion.py"
