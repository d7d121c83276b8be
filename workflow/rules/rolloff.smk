# Roll-off (Section 2.4): port spot vs field angle, even polynomial per band and medium.


rule rolloff:
    input:
        frames=rolloff_inputs,
        geometry=expand("results/geometry/{lens}.nc", lens=LENSES),
    output:
        artefacts=expand("results/rolloff/{lens}.nc", lens=LENSES),
    params:
        dataset=config["dataset"],
        lenses=LENSES,
        config=stage_params(config, "rolloff"),
    conda:
        "../envs/pipeline.yaml"
    log:
        "results/logs/rolloff.log",
    benchmark:
        "results/benchmarks/rolloff.tsv"
    script:
        "../scripts/rolloff.py"
