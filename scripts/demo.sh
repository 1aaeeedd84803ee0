#!/usr/bin/env bash
# The main job on the embedded default: set up, then train the demo scene on CPU.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/bootstrap.sh
. .venv/bin/activate
# write bytecode caches even where PYTHONDONTWRITEBYTECODE is set: uv installs packages
# without them, and each run would otherwise compile ~1,250 modules again (~4 s)
unset PYTHONDONTWRITEBYTECODE
glint demo "$@"
