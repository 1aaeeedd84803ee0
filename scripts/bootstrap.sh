#!/usr/bin/env bash
# Create .venv (if missing) and install Glint with its dev tools.
# torch is installed first (BOOTSTRAP_TORCH_VERSION, default 2.13.0: the CPU build this machine ships), so that
# no resolver ever pulls a CUDA build; every other package's torch range accepts it.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
    "$PY" -m venv .venv
fi
. .venv/bin/activate
python -m pip install -q --upgrade pip >/dev/null
if ! python -c "import torch" 2>/dev/null; then
    # --no-compile: pip would byte-compile all of torch's files on one core (29 s of 36 here);
    # the modules Glint imports get their caches on first import instead (scripts/test.sh
    # and scripts/demo.sh let Python write them), as uv leaves it for every other package
    python -m pip install -q --no-compile "torch==${BOOTSTRAP_TORCH_VERSION:-2.13.0}"
fi
# the HTTP client (client/, distribution glint-client) adds `glint remote` to `glint`.
# uv resolves and installs the rest in seconds where pip takes a minute (it keeps the torch installed above,
# whose version every range admits); pip is the fallback wherever uv cannot be installed or fails.
if python -m pip install -q uv >/dev/null 2>&1 && python -m uv pip install -q -e ".[dev]" -e ./client; then
    :
else
    echo "bootstrap: uv unavailable or failed; installing with pip" >&2
    python -m pip install -q -e ".[dev]" -e ./client
fi
