#!/usr/bin/env bash
# The test command: sets up everything on a fresh machine, then lints and tests.
#   venv + packages (scripts/bootstrap.sh), services the integration tests talk to
#   (scripts/services.sh: Redis), a browser for the viewer tests (scripts/browser.sh:
#   Debian's Chromium), then ruff and pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/bootstrap.sh
. .venv/bin/activate
# bytecode caches: uv installs packages without .pyc files, and an environment with
# PYTHONDONTWRITEBYTECODE set (this machine's, CI's) then compiles ~1,250 modules from
# source in every Python process the suite starts (servers, jobs, CLI runs: ~4 s each
# on 2 cores). Unset here, the first import writes each cache and the rest read it.
unset PYTHONDONTWRITEBYTECODE
# numba kernels: compiled once into their cache before pytest, so the test workers and
# the servers they start load them instead of each compiling the same kernels at once
# (scripts/warm_kernels.py: every signature a test run compiles, recorded in
# scripts/kernel_signatures.tsv, in two processes; ~100 s on a fresh clone of a 2-core
# VM without AVX-512). It runs while apt and npm install the services and the browser
# below (mostly waiting on disk), not after them.
warm_log=$(mktemp)
python scripts/warm_kernels.py >"$warm_log" 2>&1 &
warm_pid=$!
for s in scripts/services.sh scripts/browser.sh scripts/gltf_validator.sh; do
    if [ -f "$s" ]; then bash "$s"; fi
done
echo "== ruff"
ruff check .
ruff format --check .
echo "== numba kernels"
if ! wait "$warm_pid"; then cat "$warm_log"; echo "warm_kernels.py failed" >&2; exit 1; fi
cat "$warm_log"
rm -f "$warm_log"
echo "== pytest"
# two workers (the machine's cores), each test file on one worker so a file's fixtures
# (servers, trained runs) are built once, longest files first (tests/file_order.py);
# PYTEST_WORKERS=0 runs everything in-process; the 25 slowest tests are listed at the
# end (where the suite's time goes, for keeping CI short)
python -m pytest -q -p no:cacheprovider -n "${PYTEST_WORKERS:-2}" --dist loadfile \
    --no-loadscope-reorder --durations=25 "$@"
