# Calibration workflow of a RAW camera as a radiometer (Larouche et al. 2024).
# Each calibration experiment is a rule that writes one versioned NetCDF
# artefact per lens; diagnostics and the report come last.

import os
import signal
import sys

from snakemake.utils import min_version

from pipeline.errors import InputError
from pipeline.runner.workflow import check_config

min_version("8.0")


configfile: os.path.join(workflow.basedir, "config", "config.yaml")


# the front page of `snakemake --report`; the figures carry their captions (workflow/rules/report.smk)
report: "workflow/report/workflow.rst"


# the config files read (a key written twice refused), src/pipeline/schema.yaml (filling its defaults),
# model.plugins and model.effects: one line and no job on a mistake
try:
    check_config(
        config,
        os.path.join(workflow.basedir, "config", "config.yaml"),
        config_files=workflow.configfiles,
    )
except InputError as exc:
    sys.exit(f"error: {exc}")

# The rules' scripts import the installed package (`make` installs this checkout into .venv; with
# --use-conda, workflow/envs/pipeline.post-deploy.sh installs it into the rules' software env).


include: "workflow/rules/common.smk"
include: "workflow/rules/dataset.smk"
include: "workflow/rules/dark.smk"
include: "workflow/rules/linearity.smk"
include: "workflow/rules/geometry.smk"
include: "workflow/rules/rolloff.smk"
include: "workflow/rules/spectral.smk"
include: "workflow/rules/absolute.smk"
include: "workflow/rules/immersion.smk"
include: "workflow/rules/calibration.smk"
include: "workflow/rules/field.smk"
include: "workflow/rules/diagnostics.smk"
include: "workflow/rules/report.smk"


rule all:
    default_target: True
    input:
        "results/report/index.html",


onstart:
    SIGNALS.watch(signal.SIGTERM)


onsuccess:
    print_run_summary()


onerror:
    report_failed_run()
