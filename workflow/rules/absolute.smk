# Absolute spectral radiance (Section 2.6, Eq. 9, Table 1): R^-1 per band with its budget.
# Input functions (common.smk): absolute_inputs (frames.csv, raw frames, source_spectrum.csv,
# source_reference.csv).


rule absolute:
    input:
        frames=absolute_inputs,
        spectral=expand("results/spectral/{lens}.nc", lens=LENSES),
        geometry=expand("results/geometry/{lens}.nc", lens=LENSES),
    output:
        artefacts=expand("results/absolute/{lens}.nc", lens=LENSES),
    params:
        dataset=config["dataset"],
        lenses=LENSES,
        config=stage_params(config, "absolute"),
    conda:
        "../envs/pipeline.yaml"
    log:
        "results/logs/absolute.log",
    benchmark:
        "results/benchmarks/absolute.tsv"
    script:
        "../scripts/absolute.py"
