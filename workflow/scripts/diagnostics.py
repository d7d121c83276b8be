"""Rule 'diagnostics': unpack the snakemake object and call the package."""

from pipeline.entry import stop_quietly_on_interrupt

stop_quietly_on_interrupt()  # first: Ctrl-C ends the job quietly, also during the imports below

from pipeline.diagnostics.missing_effects import diagnose_artefacts  # noqa: E402 (after the interrupt handler)
from pipeline.runner.workflow import exit_on_input_error, setup_log  # noqa: E402 (after the interrupt handler)

smk = snakemake  # noqa: F821 (snakemake injects this object)
setup_log(smk.log[0])
exit_on_input_error(diagnose_artefacts, {stage: list(paths) for stage, paths in smk.input.items()},
                    smk.params.config, smk.output.missing_effects, smk.output.unexplained, smk.output.run_errors,
                    smk.params.ledger, smk.output.error_history, smk.output.residual_tests, smk.output.closure,
                    smk.output.lens_tests, smk.output.field_scale, plausibility_csv=smk.output.plausibility)
