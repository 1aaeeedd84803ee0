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
# no recommends: they pull printing, audio, notification and perl desktop tools (~120
# packages) that a headless browser never loads; the fonts are the one recommend kept
$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
  chromium fonts-liberation
echo "chromium: $(/usr/bin/chromium --version 2>/dev/null || echo installed)"
