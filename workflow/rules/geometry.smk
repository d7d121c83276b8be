# Geometric calibration (Sections 2.3 and 3.2): chessboard corners, Scaramuzza fit per
# lens, medium and band, image circle and half field of view, theta/phi/solid-angle maps.


rule geometry:
    input:
        frames=geometry_inputs,
    output:
        artefacts=expand("results/geometry/{lens}.nc", lens=LENSES),
    params:
        dataset=config["dataset"],
        lenses=LENSES,
        config=stage_params(config, "geometry"),
    conda:
        "../envs/pipeline.yaml"
    log:
        "results/logs/geometry.log",
    benchmark:
        "results/benchmarks/geometry.tsv"
    script:
        "../scripts/geometry.py"
