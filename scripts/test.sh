#!/usr/bin/env bash
# The test suite: set up if needed, lint (ruff), type-check (mypy --strict), then pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/bootstrap.sh
.venv/bin/ruff check services cosmos simulation scene_assets tests tools benchmarks training
.venv/bin/ruff format --check services cosmos simulation scene_assets tests tools benchmarks training
.venv/bin/mypy
if .venv/bin/python -c "import torch" 2>/dev/null; then .venv/bin/mypy training; fi
.venv/bin/python -m tools.export_schema --check
exec .venv/bin/pytest "$@"
