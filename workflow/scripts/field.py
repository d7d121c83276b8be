"""Rule 'field': one lens; unpack the snakemake object and call the package."""

from pipeline.workflow import run_stage_script

run_stage_script(snakemake, "field")  # noqa: F821 (snakemake injects this object)
