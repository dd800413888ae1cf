#!/usr/bin/env bash
# The test command of the README: set up (idempotent), lint (ruff), then run the test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh --dev
.venv/bin/ruff check .
.venv/bin/lint-imports --no-cache >/dev/null || .venv/bin/lint-imports --no-cache  # the layers of docs/ARCHITECTURE.md, no import cycles
export PYTHONWARNINGS="${PYTHONWARNINGS:-ignore::DeprecationWarning}"
# LeRobot reads datasets through Hugging Face `datasets`, which keeps a converted copy of each one
# it loads; the tests' throw-away datasets get a throw-away cache instead of the user's.
HF_DATASETS_CACHE="$(mktemp -d)"
export HF_DATASETS_CACHE
trap 'rm -rf "$HF_DATASETS_CACHE"' EXIT
.venv/bin/python -m pytest -q -p no:cacheprovider "$@"
