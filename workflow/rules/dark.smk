# Dark frames (Section 2.8): bias, fixed pattern, dark current, hot pixels, read noise.


rule dark:
    input:
        frames=dark_inputs,
    output:
        artefacts=expand("results/dark/{lens}.nc", lens=LENSES),
    params:
        dataset=config["dataset"],
        lenses=LENSES,
        config=stage_params(config, "dark"),
    conda:
        "../envs/pipeline.yaml"
    log:
        "results/logs/dark.log",
    benchmark:
        "results/benchmarks/dark.tsv"
    script:
        "../scripts/dark.py"
