#!/usr/bin/env bash
# The test command of the README: set up (idempotent), lint (ruff), then run the test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh --dev
.venv/bin/ruff check .
export PYTHONWARNINGS="${PYTHONWARNINGS:-ignore::DeprecationWarning}"
.venv/bin/python -m pytest -q -p no:cacheprovider "$@"
