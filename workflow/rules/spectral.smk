# Relative spectral response (Section 2.5): response, effective wavelength, bandwidth.
# One job per lens: the two lenses of the camera are independent sensors.


rule spectral:
    input:
        unpack(stage_inputs("spectral")),
    output:
        artefact="results/spectral/{lens}.nc",
    log:
        "results/logs/spectral/{lens}.log",
    benchmark:
        "results/benchmarks/spectral/{lens}.tsv"
    conda:
        "../envs/pipeline.yaml"
    threads: 1
    resources:
        mem_mb=job_memory_mb("spectral"),
    params:
        dataset=config["dataset"],
        config=stage_params(config, "spectral"),
        dataset_subset=dataset_subset("spectral"),
        # the package code the job runs: editing it reruns the stage and what depends on it
        code=stage_code_sha256("spectral"),
    script:
        "../scripts/spectral.py"
