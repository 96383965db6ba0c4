#!/usr/bin/env bash
# Peer benchmark of graspd's non-rigid CPD against pycpd and rustcpd (issue 3).
# Sets up bench/.venv (pycpd==2.0.0, rustcpd==4.0.0, numpy), builds graspd in
# release, then runs bench/cpd_peer.py; arguments go to it (--json, --sizes, ...).
set -uo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/venv.sh"

# Build graspd, then run a private copy of the binary: a shared CARGO_TARGET_DIR
# may be rebuilt from another checkout while the benchmark runs.
TARGET="${CARGO_TARGET_DIR:-$ROOT/target}"
if [ -z "${GRASPD_BIN:-}" ]; then
  (cd "$ROOT" && cargo build --release -q -p graspd --bin graspd) >&2 || { log "ERROR: cargo build failed"; exit 1; }
  cp "$TARGET/release/graspd" "$VENV/graspd-bench" || exit 1
  GRASPD_BIN="$VENV/graspd-bench"
fi
exec "$PY" "$ROOT/bench/cpd_peer.py" --graspd "$GRASPD_BIN" "$@"
