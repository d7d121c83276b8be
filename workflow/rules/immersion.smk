# Immersion factor (Section 2.7): log-linear extrapolation to 0-, Eq. (11), Eq. (10).


rule immersion:
    input:
        unpack(immersion_inputs),
    output:
        artefacts=expand("results/immersion/{lens}.nc", lens=LENSES),
    params:
        dataset=config["dataset"],
        lenses=LENSES,
        config=stage_params(config, "immersion"),
    conda:
        "../envs/pipeline.yaml"
    log:
        "results/logs/immersion.log",
    benchmark:
        "results/benchmarks/immersion.tsv"
    script:
        "../scripts/immersion.py"
