#!/usr/bin/env bash
# Create (or refresh) a Python venv holding the Pulicast 2.x reference peer
# (pulicast==2.0.1 from PyPI) used by the interop tests.
#
# Usage: tests/python/setup_venv.sh [VENV_DIR]   (default: <repo>/target/pyvenv)
# Idempotent: a venv that already imports pulicast is left as it is.
# Prints the venv's python path as the last line of output.
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
VENV="${1:-$REPO/target/pyvenv}"
PY="${PYTHON:-python3}"

log() { echo "setup_venv: $*" >&2; }

# Check: can the venv import the reference package (with the Qt placeholder)?
venv_ok() {
    [ -x "$VENV/bin/python" ] || return 1
    "$VENV/bin/python" - <<'PYEOF' >/dev/null 2>&1
import sys, types
qt = types.ModuleType("pulicast.pulicast_qt")
qt.QtNode = object
sys.modules["pulicast.pulicast_qt"] = qt
import importlib.metadata
assert importlib.metadata.version("pulicast") == "2.0.1"
import pulicast, pulicast.discovery.node_discoverer, trio, numpy, tomlkit
PYEOF
}

if venv_ok; then
    log "venv at $VENV is ready"
    echo "$VENV/bin/python"
    exit 0
fi

command -v "$PY" >/dev/null || { log "no $PY found"; exit 1; }

# Never installs system packages: the machine is the caller's (.ci/run
# installs python3-venv where it is missing).
venv_missing() {
    local ver
    ver="$("$PY" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")')"
    log "$PY cannot make a venv (no venv/ensurepip): install python${ver}-venv (apt-get install python3-venv); .ci/run does"
    exit 1
}

# A half-made venv (no python or no pip) is rebuilt from scratch.
if [ -e "$VENV" ] && ! "$VENV/bin/python" -m pip --version >/dev/null 2>&1; then
    log "removing broken venv at $VENV"
    rm -rf "$VENV"
fi
if [ ! -x "$VENV/bin/python" ]; then
    log "creating venv at $VENV"
    mkdir -p "$(dirname "$VENV")"
    # On Debian's own python3 `-m venv` fails without the pythonX.Y-venv
    # package (no ensurepip wheels).
    if ! "$PY" -m venv "$VENV"; then
        rm -rf "$VENV"
        venv_missing
    fi
fi

PIP=("$VENV/bin/python" -m pip --disable-pip-version-check -q)
export PIP_NO_INPUT=1
# The reference package requires PySide2 and qtrio (no PySide2 wheel for current
# Pythons): skip its declared deps and install what it needs at import time (trio;
# numpy as the project brief asks; tomlkit for pulicast_tools.puliconf). pip then warns that PySide2/qtrio are missing:
# expected, the peer puts a placeholder module in place of pulicast.pulicast_qt.
"${PIP[@]}" install --no-deps "pulicast==2.0.1"
out="$(mktemp)"
if ! "${PIP[@]}" install trio numpy tomlkit >"$out" 2>&1; then
    cat "$out" >&2; rm -f "$out"; exit 1
fi
grep -v "PySide2\|qtrio\|dependency resolver\|dependency conflicts" "$out" >&2 || true
rm -f "$out"

if ! venv_ok; then
    log "venv at $VENV still cannot import pulicast; error follows"
    "$VENV/bin/python" -c '
import sys, types
qt = types.ModuleType("pulicast.pulicast_qt"); qt.QtNode = object
sys.modules["pulicast.pulicast_qt"] = qt
import pulicast, pulicast.discovery.node_discoverer' || true
    exit 1
fi
log "venv at $VENV is ready"
echo "$VENV/bin/python"
