#!/usr/bin/env bash
# Peer benchmark of graspd's non-rigid CPD against pycpd and rustcpd (issue 3).
# Sets up bench/.venv (pycpd==2.0.0, rustcpd==4.0.0, numpy), builds graspd in
# release, then runs bench/cpd_peer.py; arguments go to it (--json, --sizes, ...).
set -uo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$ROOT/bench/.venv"
log() { echo "$*" >&2; }

if [ ! -x "$VENV/bin/python" ]; then
  log "creating $VENV"
  python3 -m venv "$VENV" || { log "ERROR: python3 -m venv failed"; exit 1; }
fi
PY="$VENV/bin/python"
"$PY" -m pip install -q --disable-pip-version-check numpy >&2 || { log "ERROR: numpy failed to install; cannot run"; exit 1; }
for pkg in pycpd==2.0.0 rustcpd==4.0.0; do
  name="${pkg%%==*}"; want="${pkg##*==}"
  have="$("$PY" -c "from importlib.metadata import version; print(version('$name'))" 2>/dev/null)"
  if [ "$have" != "$want" ]; then
    if ! "$PY" -m pip install -q --disable-pip-version-check "$pkg" >&2; then
      log "WARNING: could not install $pkg from PyPI; its rows will be skipped"
    fi
  fi
done

# Build graspd, then run a private copy of the binary: a shared CARGO_TARGET_DIR
# may be rebuilt from another checkout while the benchmark runs.
TARGET="${CARGO_TARGET_DIR:-$ROOT/target}"
if [ -z "${GRASPD_BIN:-}" ]; then
  (cd "$ROOT" && cargo build --release -q -p graspd --bin graspd) >&2 || { log "ERROR: cargo build failed"; exit 1; }
  cp "$TARGET/release/graspd" "$VENV/graspd-bench" || exit 1
  GRASPD_BIN="$VENV/graspd-bench"
fi
exec "$PY" "$ROOT/bench/cpd_peer.py" --graspd "$GRASPD_BIN" "$@"
