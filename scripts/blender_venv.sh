#!/usr/bin/env bash
# Create .venv-blender: Blender as a Python module (PyPI `bpy`, several hundred MB) plus
# numpy, for the Blender side of `python -m bench.blender_asset` (bench/blender_render.py).
# Kept apart from .venv on purpose: bpy is never a dependency of Glint, its tests or CI.
# bpy 4.5 LTS wheels are built for CPython 3.11 only (Linux x86-64/arm64, macOS, Windows).
# Usage: bash scripts/blender_venv.sh [DEST]   (default .venv-blender, git-ignored)
#   BPY_VERSION=4.5.15 (default) picks the wheel; PYTHON=python3.11 the interpreter.
set -euo pipefail
cd "$(dirname "$0")/.."
DEST=${1:-.venv-blender}
PY=${PYTHON:-python3.11}
if [ ! -x "$DEST/bin/python" ]; then
    "$PY" -m venv "$DEST"
fi
"$DEST/bin/python" -m pip install -q --upgrade pip >/dev/null
"$DEST/bin/python" -m pip install -q "bpy==${BPY_VERSION:-4.5.15}" "numpy<3"
"$DEST/bin/python" - <<'PY'
import bpy
print("bpy", bpy.app.version_string, "ready")
PY
