# Linearity (Section 2.2): Pearson maps, sweeps, saturation, photon transfer.
# One job per lens: the two lenses of the camera are independent sensors.


rule linearity:
    input:
        unpack(stage_inputs("linearity")),
    output:
        artefact="results/linearity/{lens}.nc",
    log:
        "results/logs/linearity/{lens}.log",
    benchmark:
        "results/benchmarks/linearity/{lens}.tsv"
    conda:
        "../envs/pipeline.yaml"
    threads: 1
    resources:
        mem_mb=job_memory_mb("linearity"),
    params:
        dataset=config["dataset"],
        config=stage_params(config, "linearity"),
        dataset_subset=dataset_subset("linearity"),
        # the package code the job runs: editing it reruns the stage and what depends on it
        code=stage_code_sha256("linearity"),
    script:
        "../scripts/linearity.py"
