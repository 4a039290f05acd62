#!/usr/bin/env bash
# The demo: set up if needed, then run it end to end on the built-in demo scene.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/bootstrap.sh
exec .venv/bin/cosmos demo "$@"
