#!/usr/bin/env bash
# GPU acceptance kit (bench/gpu_check.py): proves the CUDA path and measures it.
#
# On a bare GPU machine (Python 3.12 with a CUDA torch and nvcc, no package index),
# with the folder scripts/gpu_wheels.sh made here carried along:
#   bash scripts/gpu_check.sh --wheels .gpu-wheels --out gpu-report
# (stages resume: run it again until the report lists none as pending)
#
# Anywhere, in CPU form (CI runs this through tests/test_gpu_kit.py):
#   bash scripts/gpu_check.sh --dry-run --out /tmp/gpu-dry
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ -x .venv/bin/python ]; then PY=.venv/bin/python; fi
export PYTHONPATH="$PWD:$PWD/client${PYTHONPATH:+:$PYTHONPATH}"  # the repo and its client package
exec "$PY" -m bench.gpu_check "$@"
