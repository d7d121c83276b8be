"""Rule 'simulate_dataset': unpack the snakemake object and call the simulator's entry point."""

from pipeline.cli import simulate_from_config
from pipeline.workflow import exit_on_input_error, setup_log

setup_log(snakemake.log[0])  # noqa: F821 (snakemake injects this object)
exit_on_input_error(simulate_from_config, snakemake.output.dataset, snakemake.params.simulation)  # noqa: F821
