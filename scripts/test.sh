#!/usr/bin/env bash
# Set up (or update) .venv, lint with ruff (pyproject.toml's [tool.ruff]), then run the whole test suite,
# slow end-to-end tests included, offline.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/bootstrap.sh
.venv/bin/python -m ruff check .
export HF_HUB_OFFLINE=1 PYTHONUNBUFFERED=1
exec .venv/bin/python -m pytest -q "$@"
