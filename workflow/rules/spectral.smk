# Relative spectral response (Section 2.5): response, effective wavelength, bandwidth.
# Input functions (common.smk): spectral_inputs (frames.csv, raw frames, photodiode.csv).


rule spectral:
    input:
        frames=spectral_inputs,
        geometry=expand("results/geometry/{lens}.nc", lens=LENSES),
    output:
        artefacts=expand("results/spectral/{lens}.nc", lens=LENSES),
    params:
        dataset=config["dataset"],
        lenses=LENSES,
        config=stage_params(config, "spectral"),
    conda:
        "../envs/pipeline.yaml"
    log:
        "results/logs/spectral.log",
    benchmark:
        "results/benchmarks/spectral.tsv"
    script:
        "../scripts/spectral.py"
