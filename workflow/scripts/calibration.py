"""Rule 'calibration': unpack the snakemake object and call the package."""

from pipeline.entry import stop_quietly_on_interrupt

stop_quietly_on_interrupt()  # first: Ctrl-C ends the job quietly, also during the imports below

from pipeline.bundle.calibration import build_bundle_script  # noqa: E402 (after the interrupt handler)

build_bundle_script(snakemake)  # noqa: F821 (snakemake injects this object)
