"""Rule 'calibration': unpack the snakemake object and call the package."""

from pipeline.calibration import build_bundle_script

build_bundle_script(snakemake)  # noqa: F821 (snakemake injects this object)
