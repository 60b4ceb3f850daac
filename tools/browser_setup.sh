#!/bin/sh
# Debian's Chromium, the headless browser the report test (tests/test_report_browser.py) loads
# report.html in. Installed when missing (needs root and apt-get); without it the test fails
# under CI and is skipped elsewhere, saying how to install it.
# And the Khronos glTF validator (tests/test_mesh.py checks the mesh's .glb with it), from npm, in
# tools/node_modules: installed once where node and npm are; without it that test is skipped.
set -eu
here=$(dirname "$0")
if [ ! -d "$here/node_modules/gltf-validator" ] && command -v npm >/dev/null 2>&1; then
    npm install --silent --no-audit --no-fund --no-save --prefix "$here" gltf-validator@2.0.0-dev.3.10 >/dev/null 2>&1 ||
        echo "note: the glTF validator could not be installed (npm install gltf-validator)" >&2
fi
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
