#!/usr/bin/env bash
# Run by the workflow inside the rules' software env once it is created (snakemake --use-conda): installs
# the project's own package, without touching the dependencies the env file pinned. The working directory
# is the one the workflow runs in, the checkout's root.
set -euo pipefail
python -m pip install --no-deps .
