#!/bin/sh
# Debian's Chromium, the headless browser the report test (tests/test_report_browser.py) loads
# report.html in. Installed when missing (needs root and apt-get); without it the test fails
# under CI and is skipped elsewhere, saying how to install it.
set -eu
if command -v chromium >/dev/null 2>&1; then
    exit 0
fi
if [ "$(id -u)" != 0 ] || ! command -v apt-get >/dev/null 2>&1; then
    echo "note: chromium is not installed (the report's browser test needs it): run 'make test' as root," \
         "or 'apt-get install chromium'" >&2
    exit 0
fi
echo "installing Debian's chromium (for the report's browser test) ..."
export DEBIAN_FRONTEND=noninteractive
apt-get install -y -q --no-install-recommends chromium >/dev/null 2>&1 ||
    { apt-get update -q >/dev/null && apt-get install -y -q --no-install-recommends chromium >/dev/null; }
command -v chromium >/dev/null 2>&1 || { echo "error: chromium still not installed" >&2; exit 1; }
