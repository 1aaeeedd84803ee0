#!/usr/bin/env bash
# Make sure what the integration tests need is present: the redis-server binary
# (tests start their own servers on free ports) and wrk (the load test). Idempotent and
# non-interactive.
set -euo pipefail

SUDO=""
if [ "$(id -u)" -ne 0 ]; then
    SUDO="sudo -n"
fi
export DEBIAN_FRONTEND=noninteractive
updated=""
apt_install() {  # one `apt-get update` at most, only when something is missing
    if [ -z "$updated" ]; then $SUDO apt-get update -q; updated=1; fi
    $SUDO apt-get install -y -q --no-install-recommends "$@"
}

if command -v redis-server >/dev/null 2>&1; then
    echo "services: redis-server present ($(redis-server --version | head -n1))"
else
    echo "services: installing redis-server"
    apt_install redis-server
    # the package may start a system service; the tests do not need it
    command -v redis-server >/dev/null 2>&1
    echo "services: redis-server installed ($(redis-server --version | head -n1))"
fi

# wrk drives the API load test's closed loop (tests/test_bench_api_load.py)
if command -v wrk >/dev/null 2>&1; then
    echo "services: wrk present"
else
    echo "services: installing wrk"
    apt_install wrk
fi
