#!/bin/sh
# QGIS 3.40 LTR (Debian bookworm-backports) and .venv-qgis, the environment the
# QGIS tests run in: Debian's Python (the one QGIS's bindings are built for),
# geoortho installed with tools/qgis-constraints.txt, Debian's dist-packages
# (qgis, PyQt5, processing's dependencies) visible *after* the venv's own.
# Usage: tools/qgis_setup.sh [VENV]      (installing QGIS needs root)
set -eu
venv=${1:-.venv-qgis}
here=$(cd "$(dirname "$0")" && pwd)
project=$(dirname "$here")

qgis_ok() {
    command -v qgis_process >/dev/null 2>&1 &&
        dpkg-query -W -f='${Version}' python3-qgis 2>/dev/null | grep -q '^3\.40'
}
if ! qgis_ok; then
    if [ "$(id -u)" != 0 ] || ! command -v apt-get >/dev/null 2>&1; then
        echo "error: QGIS 3.40 is not installed, and installing it needs root and apt-get;" \
             "run 'make test-qgis' as root, or install qgis python3-qgis from bookworm-backports" >&2
        exit 1
    fi
    echo "installing QGIS 3.40 LTR from bookworm-backports ..."
    export DEBIAN_FRONTEND=noninteractive
    mirror=$(awk '/^URIs:/{print $2; exit}' /etc/apt/sources.list.d/debian.sources 2>/dev/null || true)
    [ -n "$mirror" ] || mirror=$(awk '/^deb .* bookworm /{print $2; exit}' /etc/apt/sources.list 2>/dev/null || true)
    [ -n "$mirror" ] || mirror=http://deb.debian.org/debian
    echo "deb $mirror bookworm-backports main" > /etc/apt/sources.list.d/bookworm-backports.list
    apt-get update -q >/dev/null
    apt-get install -y -q --no-install-recommends -t bookworm-backports \
        qgis python3-qgis python3-venv >/dev/null
    qgis_ok || { echo "error: QGIS 3.40 still not installed" >&2; exit 1; }
fi

site_pth() {
    echo "$("$venv/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')/zz-debian-dist-packages.pth"
}
stamp="$venv/.installed-stamp"
if [ ! -f "$stamp" ] || [ "$project/pyproject.toml" -nt "$stamp" ] || [ "$here/qgis-constraints.txt" -nt "$stamp" ]; then
    [ -x "$venv/bin/python" ] || /usr/bin/python3 -m venv "$venv"
    # Hidden while pip works: pip would count Debian's old packages as installed.
    rm -f "$(site_pth)"
    "$venv/bin/python" -m pip install --quiet --upgrade pip
    "$venv/bin/python" -m pip install --quiet -c "$here/qgis-constraints.txt" -e "$project" "pytest>=8"
    touch "$stamp"
fi
echo /usr/lib/python3/dist-packages > "$(site_pth)"
QT_QPA_PLATFORM=offscreen "$venv/bin/python" -c \
    'from qgis.core import Qgis; import numpy, shapely; print("QGIS", Qgis.version(), "numpy", numpy.__version__, "shapely", shapely.__version__)'
