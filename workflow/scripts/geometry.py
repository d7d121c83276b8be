"""Rule 'geometry': one lens; unpack the snakemake object and call the package."""

from pipeline.entry import stop_quietly_on_interrupt

stop_quietly_on_interrupt()  # first: Ctrl-C ends the job quietly, also during the imports below

from pipeline.runner.workflow import run_stage_script  # noqa: E402 (after the interrupt handler)

run_stage_script(snakemake, "geometry")  # noqa: F821 (snakemake injects this object)
