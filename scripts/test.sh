#!/usr/bin/env bash
# The test command of the README: set up (idempotent) and run the test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh --dev
export PYTHONWARNINGS="${PYTHONWARNINGS:-ignore::DeprecationWarning}"
.venv/bin/python -m pytest -q -p no:cacheprovider "$@"
