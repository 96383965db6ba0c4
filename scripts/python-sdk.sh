#!/usr/bin/env bash
# Makes the Python SDK's virtual environment, client/python/.venv (gitignored):
# iceoryx2 0.10.0 (the same release as the daemon's Rust crate), NumPy and
# pytest from PyPI, and the SDK itself (graspd_client, from client/python) and
# the simulator's Python environments (graspd_sim, from sim/python; it loads
# target/release/libgraspd_sim_ffi.so) installed in editable mode, so their
# tests and a user's scripts import them.
#
# Idempotent: an environment that already imports everything is kept. Needs
# python3 (3.9+) with the venv module and network access to PyPI on the
# first run. The end-to-end test tests/daemon.rs::the_python_sdk_* runs the
# SDK's tests with this environment.
set -euo pipefail
cd "$(dirname "$0")/.."

PY="${PYTHON:-python3}"
VENV=client/python/.venv
STAMP="$VENV/.graspd-sdk-2"

if [ -x "$VENV/bin/python" ] && [ -f "$STAMP" ] \
    && "$VENV/bin/python" -c "import iceoryx2, numpy, pytest, graspd_client, graspd_sim" 2>/dev/null; then
    echo "Python SDK environment: $(cd "$VENV" && pwd)" >&2
    exit 0
fi

if ! "$PY" -m venv "$VENV" 2>/dev/null; then
    # Debian's python3 leaves the venv module's ensurepip in a package of its own.
    if command -v apt-get >/dev/null && [ "$(id -u)" = 0 ]; then
        echo "installing python3-venv (Debian) ..." >&2
        apt-get update -qq >&2 && apt-get install -y -qq python3-venv >&2
        "$PY" -m venv "$VENV"
    else
        echo "error: $PY -m venv failed; install python3-venv" >&2
        exit 1
    fi
fi
echo "installing iceoryx2==0.10.0, numpy, pytest, graspd_client and graspd_sim into $VENV ..." >&2
"$VENV/bin/python" -m pip install -q --upgrade pip >&2
"$VENV/bin/python" -m pip install -q "iceoryx2==0.10.0" numpy pytest >&2
"$VENV/bin/python" -m pip install -q -e client/python -e sim/python >&2
touch "$STAMP"
echo "Python SDK environment: $(cd "$VENV" && pwd)" >&2
