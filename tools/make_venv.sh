#!/bin/sh
# Create a virtual environment, installing Debian's python3-venv first when the
# interpreter cannot make one (a bare Debian 12 ships python3 without ensurepip).
set -eu
python=${1:-python3}
venv=${2:-.venv}
# The EGM96 geoid grid (orthometric <-> ellipsoidal heights) is Debian's proj-data; pyproj's wheel
# carries no grids.
if [ ! -f /usr/share/proj/egm96_15.gtx ] && [ ! -f /usr/share/proj/us_nga_egm96_15.tif ]; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
        echo "installing proj-data (EGM96 geoid grid) ..."
        DEBIAN_FRONTEND=noninteractive apt-get update -q >/dev/null
        DEBIAN_FRONTEND=noninteractive apt-get install -y -q proj-data >/dev/null
    else
        echo "warning: no EGM96 geoid grid; install Debian's proj-data (apt-get install proj-data)" >&2
    fi
fi
if [ -x "$venv/bin/python" ] && "$venv/bin/python" -m pip --version >/dev/null 2>&1; then
    exit 0
fi
rm -rf "$venv"
if ! "$python" -m venv "$venv" 2>/dev/null; then
    rm -rf "$venv"
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
        echo "installing python3-venv (Debian) ..."
        DEBIAN_FRONTEND=noninteractive apt-get update -q >/dev/null
        DEBIAN_FRONTEND=noninteractive apt-get install -y -q python3-venv >/dev/null
        "$python" -m venv "$venv"
    else
        echo "error: '$python -m venv' failed; install python3-venv (apt-get install python3-venv)" >&2
        exit 1
    fi
fi
