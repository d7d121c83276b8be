"""Rule 'simulate_dataset': unpack the snakemake object and call the simulator's entry point."""

from pipeline.entry import stop_quietly_on_interrupt

stop_quietly_on_interrupt()  # first: Ctrl-C ends the job quietly, also during the imports below

from pipeline.cli import simulate_from_config  # noqa: E402 (after the interrupt handler)
from pipeline.runner.workflow import exit_on_input_error, setup_log  # noqa: E402 (after the interrupt handler)

setup_log(snakemake.log[0])  # noqa: F821 (snakemake injects this object)
exit_on_input_error(simulate_from_config, snakemake.output.dataset, snakemake.params.simulation)  # noqa: F821
