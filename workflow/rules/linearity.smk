# Linearity (Section 2.2): Pearson maps, sweeps, saturation, photon transfer.


rule linearity:
    input:
        frames=linearity_inputs,
        dark=expand("results/dark/{lens}.nc", lens=LENSES),
    output:
        artefacts=expand("results/linearity/{lens}.nc", lens=LENSES),
    params:
        dataset=config["dataset"],
        lenses=LENSES,
        config=stage_params(config, "linearity"),
    conda:
        "../envs/pipeline.yaml"
    log:
        "results/logs/linearity.log",
    benchmark:
        "results/benchmarks/linearity.tsv"
    script:
        "../scripts/linearity.py"
