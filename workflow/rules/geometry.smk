# Geometric calibration (Sections 2.3 and 3.2): chessboard corners, Scaramuzza fit per
# medium and band, image circle and half field of view, theta/phi/solid-angle maps.
# One job per lens: the two lenses of the camera are independent sensors.


rule geometry:
    input:
        unpack(stage_inputs("geometry")),
    output:
        artefact="results/geometry/{lens}.nc",
    log:
        "results/logs/geometry/{lens}.log",
    benchmark:
        "results/benchmarks/geometry/{lens}.tsv"
    conda:
        "../envs/pipeline.yaml"
    threads: 1
    resources:
        mem_mb=job_memory_mb("geometry"),
    params:
        dataset=config["dataset"],
        config=stage_params(config, "geometry"),
        dataset_subset=dataset_subset("geometry"),
        # the package code the job runs: editing it reruns the stage and what depends on it
        code=stage_code_sha256("geometry"),
    script:
        "../scripts/geometry.py"
