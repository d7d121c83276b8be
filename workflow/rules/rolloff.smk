# Roll-off (Section 2.4): port spot vs field angle, even polynomial per band and medium.
# One job per lens: the two lenses of the camera are independent sensors.


rule rolloff:
    input:
        unpack(stage_inputs("rolloff")),
    output:
        artefact="results/rolloff/{lens}.nc",
    log:
        "results/logs/rolloff/{lens}.log",
    benchmark:
        "results/benchmarks/rolloff/{lens}.tsv"
    conda:
        "../envs/pipeline.yaml"
    threads: 1
    resources:
        mem_mb=job_memory_mb("rolloff"),
    params:
        dataset=config["dataset"],
        config=stage_params(config, "rolloff"),
        dataset_subset=dataset_subset("rolloff"),
        # the package code the job runs: editing it reruns the stage and what depends on it
        code=stage_code_sha256("rolloff"),
    script:
        "../scripts/rolloff.py"
