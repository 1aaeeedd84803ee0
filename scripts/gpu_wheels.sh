#!/usr/bin/env bash
# Make the folder the GPU kit carries to a GPU machine: the locked x86-64 cp312 wheels
# (scripts/gpu/wheels.lock.json, about 27 MiB; never torch) and a redis-server binary
# for the worker round trip. Refresh the lock after changing dependencies with
#   .venv/bin/python -m bench.gpu_wheels --lock
# Usage: bash scripts/gpu_wheels.sh [DEST]   (default .gpu-wheels, git-ignored)
set -euo pipefail
cd "$(dirname "$0")/.."
DEST=${1:-.gpu-wheels}
bash scripts/bootstrap.sh
.venv/bin/python -m bench.gpu_wheels --check
.venv/bin/python -m bench.gpu_wheels --fetch "$DEST"
if command -v redis-server >/dev/null; then
  cp "$(command -v redis-server)" "$DEST/"
  # the libraries it needs that a CUDA image lacks (jemalloc, lzf, atomic; under 1 MiB):
  # the rest (ssl, systemd, zstd, ...) are part of any Ubuntu base image
  mkdir -p "$DEST/redis-libs"
  ldd "$(command -v redis-server)" | awk '$3 ~ /^\// {print $3}' \
    | grep -E '/lib(jemalloc|lzf|atomic)\.so' | xargs -r cp -L -t "$DEST/redis-libs/"
fi
du -sh "$DEST"
