#!/usr/bin/env bash
# The README's main job: set up (idempotent), then run the shared-control demo.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/rtv3 demo "$@"
