"""Rule 'diagnostics': unpack the snakemake object and call the package."""

import sys
from pathlib import Path

try:
    from pipeline.workflow import run_stage_script
except ImportError:  # a rule's conda env has the dependencies but not this checkout's package
    sys.path.insert(0, str(Path(snakemake.scriptdir).parents[1] / "src"))  # noqa: F821
    from pipeline.workflow import run_stage_script

run_stage_script(snakemake, "diagnostics")  # noqa: F821 (snakemake injects this object)
