# Roll-off (Section 2.4): port spot vs field angle, even polynomial per band and medium.
# One job per lens: the two lenses of the camera are independent sensors.


rule rolloff:
    input:
        unpack(stage_inputs("rolloff")),
    output:
        artefact="results/rolloff/{lens}.nc",
    params:
        dataset=config["dataset"],
        config=stage_params(config, "rolloff"),
        dataset_subset=dataset_subset("rolloff"),
    threads: 1
    resources:
        mem_mb=1000,
    conda:
        "../envs/pipeline.yaml"
    log:
        "results/logs/rolloff/{lens}.log",
    benchmark:
        "results/benchmarks/rolloff/{lens}.tsv"
    script:
        "../scripts/rolloff.py"
