#!/usr/bin/env bash
# graspd retarget beside dex-retargeting 0.5.0 (PyPI), position optimiser with
# a free wrist, on our URDF and the same reachable targets, in one run.
#
#   bash bench/retarget_peer.sh            # 200 target sets, seed 1
#   N=500 SEED=7 bash bench/retarget_peer.sh
#
# Makes bench/.venv (gitignored) on first use. dex-retargeting's optimiser
# imports torch and six without declaring them, so both are installed too
# (torch from PyPI brings its CUDA wheels: a few GB, about a minute here).
set -euo pipefail
cd "$(dirname "$0")/.."
N="${N:-200}"
SEED="${SEED:-1}"
VENV=bench/.venv
PY="${PYTHON:-python3}"

if [ ! -x "$VENV/bin/python" ]; then
    "$PY" -m venv "$VENV"
fi
if ! "$VENV/bin/python" -c "import dex_retargeting.retargeting_config, torch, six" 2>/dev/null; then
    echo "installing dex-retargeting==0.5.0 (+ torch, six) into $VENV ..." >&2
    if ! "$VENV/bin/pip" install -q "dex-retargeting==0.5.0" torch six >&2; then
        echo "PEER NOT RUN: dex-retargeting==0.5.0 (with torch and six) could not be installed from PyPI into $VENV." >&2
        echo "graspd's own figures follow; compare them with shared/reference/peers.md." >&2
        INSTALL_FAILED=1
    fi
fi

cargo build --release -q -p graspd
BIN="${CARGO_TARGET_DIR:-target}/release/graspd"
TMP="$(mktemp -d)"
trap 'rm -rf "$TMP"' EXIT
"$BIN" hand sample --n "$N" --seed "$SEED" --json > "$TMP/samples.json"
"$BIN" hand info --json > "$TMP/hand.json"
"$BIN" retarget --keypoints "$TMP/samples.json" --json > "$TMP/ours.json"

if [ "${INSTALL_FAILED:-0}" = 1 ]; then
    "$VENV/bin/python" -c "import json,sys; print(json.dumps(json.load(open(sys.argv[1]))['summary'], indent=2))" "$TMP/ours.json" 2>/dev/null \
        || python3 -c "import json,sys; print(json.dumps(json.load(open(sys.argv[1]))['summary'], indent=2))" "$TMP/ours.json"
    exit 1
fi
OMP_NUM_THREADS=1 "$VENV/bin/python" bench/retarget_peer.py \
    --samples "$TMP/samples.json" --hand "$TMP/hand.json" \
    --urdf assets/hands/sih_right/sih_right.urdf --ours "$TMP/ours.json" "$@"
