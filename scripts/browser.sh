#!/usr/bin/env bash
# Install Debian's Chromium for the viewer's browser tests (idempotent).
# Playwright drives /usr/bin/chromium; it never downloads a browser of its own.
set -euo pipefail

if [ -x /usr/bin/chromium ]; then
  echo "chromium: $(/usr/bin/chromium --version 2>/dev/null || echo present)"
  exit 0
fi
SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
$SUDO apt-get update -qq
$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium
echo "chromium: $(/usr/bin/chromium --version 2>/dev/null || echo installed)"
