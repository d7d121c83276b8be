#!/usr/bin/env bash
# Headless Chromium from Debian's packages, for the test that renders the HTML report in a real browser
# (tests/runner/test_workflow_default.py opens the report in it; docs/tests.md). Rerunnable: does nothing when a Chromium is already on
# the PATH. Needs root to install (as CI has); without root and without Chromium it says so and stops,
# and the browser test is then skipped with one line saying that no Chromium was found.
set -euo pipefail

for name in chromium chromium-browser; do
    if command -v "$name" >/dev/null; then
        echo "install_browser: $name is installed ($(command -v "$name"))"
        exit 0
    fi
done
[[ $(id -u) -eq 0 ]] || { echo "install_browser: no Chromium on the PATH and not root: cannot install it" >&2; exit 1; }
command -v apt-get >/dev/null || { echo "install_browser: no Chromium on the PATH and no apt-get to install it" >&2; exit 1; }
echo "install_browser: installing Debian's chromium package"
export DEBIAN_FRONTEND=noninteractive
apt-get update -q
apt-get install -y -q --no-install-recommends chromium
command -v chromium >/dev/null || { echo "install_browser: chromium still not on the PATH after apt-get" >&2; exit 1; }
echo "install_browser: $(chromium --version 2>/dev/null)"
