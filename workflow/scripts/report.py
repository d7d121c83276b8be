"""Rule 'report': unpack the snakemake object and call the package."""

from pipeline.entry import stop_quietly_on_interrupt

stop_quietly_on_interrupt()  # first: Ctrl-C ends the job quietly, also during the imports below

from pipeline.report import build_report  # noqa: E402 (after the interrupt handler)
from pipeline.runner.workflow import STAGES, artefacts_by_lens, exit_on_input_error, setup_log  # noqa: E402 (after the interrupt handler)

smk = snakemake  # noqa: F821 (snakemake injects this object)
setup_log(smk.log[0])
artefacts = {stage: artefacts_by_lens(smk.input[stage]) if stage in smk.input.keys() else {} for stage in STAGES}
exit_on_input_error(build_report, **artefacts, missing_effects=smk.input.missing_effects,
                    unexplained=smk.input.unexplained, run_errors=smk.input.run_errors,
                    error_history=smk.input.error_history, out_html=smk.output.html, skipped=smk.params.skipped,
                    calibration=smk.input.calibration if "calibration" in smk.input.keys() else None,
                    residual_tests=smk.input.residual_tests if "residual_tests" in smk.input.keys() else None,
                    closure=smk.input.closure if "closure" in smk.input.keys() else None,
                    lens_tests=smk.input.lens_tests if "lens_tests" in smk.input.keys() else None,
                    field_scale=smk.input.field_scale if "field_scale" in smk.input.keys() else None,
                    plausibility=smk.input.plausibility if "plausibility" in smk.input.keys() else None,
                    figures_dir=smk.output.figures, dataset=smk.params.dataset, settings=smk.params.settings)
