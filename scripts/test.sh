#!/usr/bin/env bash
# Set up (or update) .venv, then run the whole test suite, slow end-to-end tests included, offline.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/bootstrap.sh
export HF_HUB_OFFLINE=1 PYTHONUNBUFFERED=1
exec .venv/bin/python -m pytest -q "$@"
