# The calibration bundle: every stage artefact of both lenses that `apply` needs, in one
# versioned file per camera (README "Calibration bundle and apply").


rule calibration:
    input:
        unpack(calibration_inputs),
    output:
        bundle="results/calibration/{serial}.nc",
    log:
        "results/logs/calibration/{serial}.log",
    benchmark:
        "results/benchmarks/calibration/{serial}.tsv"
    conda:
        "../envs/pipeline.yaml"
    threads: 1
    resources:
        mem_mb=1500,
    params:
        camera=camera_meta,
        config=stage_params(config, "calibration"),
    script:
        "../scripts/calibration.py"
