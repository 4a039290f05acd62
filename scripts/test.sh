#!/usr/bin/env bash
# The test suite: set up if needed, lint (ruff), type-check (mypy --strict), check the layers
# (import-linter), then pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/bootstrap.sh
.venv/bin/ruff check services cosmos simulation scene_assets tests tools benchmarks training
.venv/bin/ruff format --check services cosmos simulation scene_assets tests tools benchmarks training
.venv/bin/mypy
.venv/bin/lint-imports --no-logo  # the layers and no cycle: .importlinter
if .venv/bin/python -c "import torch" 2>/dev/null; then .venv/bin/mypy training; fi
.venv/bin/python -m tools.export_schema --check
exec .venv/bin/pytest "$@"
