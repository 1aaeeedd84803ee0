#!/usr/bin/env bash
# The test command: sets up everything on a fresh machine, then lints and tests.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/bootstrap.sh
. .venv/bin/activate
echo "== ruff"
ruff check .
ruff format --check .
echo "== pytest"
python -m pytest -q -p no:cacheprovider "$@"
