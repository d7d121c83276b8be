# Field match-up (Sections 2.9 and 3.8, Eq. 12, Fig. 10): the calibration bundle applied to sky frames
# against a co-located reference radiometer. One job per lens that looks at the zenith.


rule field:
    input:
        unpack(stage_inputs("field")),
    output:
        artefact="results/field/{lens}.nc",
    log:
        "results/logs/field/{lens}.log",
    benchmark:
        "results/benchmarks/field/{lens}.tsv"
    conda:
        "../envs/pipeline.yaml"
    threads: 1
    resources:
        mem_mb=job_memory_mb("field"),
    params:
        dataset=config["dataset"],
        config=stage_params(config, "field"),
        dataset_subset=dataset_subset("field"),
        # the package code the job runs: editing it reruns the stage and what depends on it
        code=stage_code_sha256("field"),
    script:
        "../scripts/field.py"
