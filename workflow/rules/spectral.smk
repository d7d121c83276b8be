# Relative spectral response (Section 2.5): response, effective wavelength, bandwidth.
# One job per lens: the two lenses of the camera are independent sensors.


rule spectral:
    input:
        unpack(stage_inputs("spectral")),
    output:
        artefact="results/spectral/{lens}.nc",
    params:
        dataset=config["dataset"],
        config=stage_params(config, "spectral"),
        dataset_subset=dataset_subset("spectral"),
    threads: 1
    resources:
        mem_mb=1000,
    conda:
        "../envs/pipeline.yaml"
    log:
        "results/logs/spectral/{lens}.log",
    benchmark:
        "results/benchmarks/spectral/{lens}.tsv"
    script:
        "../scripts/spectral.py"
