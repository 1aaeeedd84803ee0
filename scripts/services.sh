#!/usr/bin/env bash
# Make sure what the integration tests need is present: the redis-server binary
# (tests start their own servers on free ports). Idempotent and non-interactive.
set -euo pipefail

if command -v redis-server >/dev/null 2>&1; then
    echo "services: redis-server present ($(redis-server --version | head -n1))"
    exit 0
fi

echo "services: installing redis-server"
SUDO=""
if [ "$(id -u)" -ne 0 ]; then
    SUDO="sudo -n"
fi
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -q
$SUDO apt-get install -y -q --no-install-recommends redis-server
# the package may start a system service; the tests do not need it
command -v redis-server >/dev/null 2>&1
echo "services: redis-server installed ($(redis-server --version | head -n1))"
