#!/usr/bin/env bash
# The main job on the embedded default: set up, then train the demo scene on CPU.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/bootstrap.sh
. .venv/bin/activate
glint demo "$@"
