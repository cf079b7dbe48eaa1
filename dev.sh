#!/usr/bin/env bash
# Set-up and the two jobs of the README:
#   ./dev.sh demo   system packages + venv + install, then simulate a small flight and georectify it
#   ./dev.sh test   system packages + venv + install (with test extras), then the test suite
# Works on a fresh Debian machine with Python 3.11 (uses sudo for apt when not root).
set -euo pipefail
cd "$(dirname "$0")"
PY=${PYTHON:-python3}
VENV=${VENV:-.venv}

system_packages() {
    # Headless OpenGL (EGL + Mesa llvmpipe) and venv support, plus the packages given (the test job:
    # Debian's chromium, which the viewer's browser test drives through Playwright).
    local pkgs="libegl1 libgl1 libegl-mesa0 libgl1-mesa-dri python3-venv proj-data $*"
    local missing=""
    if command -v dpkg-query >/dev/null 2>&1; then
        for p in $pkgs; do
            dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing="$missing $p"
        done
    fi
    if [ -n "$missing" ]; then
        local sudo=""
        [ "$(id -u)" -eq 0 ] || sudo="sudo"
        echo "installing system packages:$missing"
        $sudo apt-get update -qq
        DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq $missing >/dev/null
    fi
}

python_env() {
    local extras=$1
    [ -x "$VENV/bin/python" ] || "$PY" -m venv "$VENV"
    "$VENV/bin/python" -m pip install -q --upgrade pip
    "$VENV/bin/python" -m pip install -q -e ".$extras"
}

case "${1:-}" in
    demo)
        system_packages
        python_env ""
        "$VENV/bin/archive" simulate demo/flight --overwrite
        "$VENV/bin/archive" render demo/flight --fov 47.5 --gsd 0.25 --out demo/mosaic.tif \
            --quicklook demo/quicklook.png --provenance --overwrite
        echo "demo: mosaic in demo/mosaic.tif (STAC Item demo/mosaic.tif.json, provenance layers" \
             "demo/mosaic_provenance.tif), preview in demo/quicklook.png"
        "$VENV/bin/archive" ingest demo/flight --archive demo/archive --fov 47.5 --overwrite --quiet >/dev/null
        echo "demo: browse the demo archive in a web browser: $VENV/bin/archive view --archive demo/archive"
        ;;
    test)
        # no 'playwright install': the browser comes from Debian; slurm-wlm and munge: tests/test_slurm.py
        # starts a one-node Slurm (as root; skipped otherwise)
        system_packages chromium slurm-wlm munge
        python_env "[test]"
        shift
        "$VENV/bin/python" -m pytest -q "$@"
        ;;
    *)
        echo "usage: ./dev.sh demo | ./dev.sh test [pytest args]" >&2
        exit 2
        ;;
esac
