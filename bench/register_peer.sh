#!/usr/bin/env bash
# Peer benchmark of graspd's registration of partial views against rustcpd's
# shape-model (atlas) fit with its global pose search (issue 3). Sets up
# bench/.venv, builds and runs examples/register_peer (graspd's shape model,
# the test views and graspd's own timed fits, written to a temporary folder),
# then bench/register_peer.py fits the same model to the same views with
# rustcpd. Arguments go to register_peer.py (--categories, --stride, --json).
# REPEATS=N times each of graspd's fits N times (default 5).
set -uo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/venv.sh"
# One thread each: the issue's registration target is single-threaded.
export RAYON_NUM_THREADS=1 OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1

CATEGORIES="mug,drill,hammer"
prev=""
for a in "$@"; do
  [ "$prev" = "--categories" ] && CATEGORIES="$a"
  case "$a" in --categories=*) CATEGORIES="${a#--categories=}" ;; esac
  prev="$a"
done
TARGET="${CARGO_TARGET_DIR:-$ROOT/target}"
(cd "$ROOT" && cargo build --release -q -p graspd --example register_peer) >&2 || { log "ERROR: cargo build failed"; exit 1; }
OUT="$(mktemp -d)"
trap 'rm -rf "$OUT"' EXIT
for c in ${CATEGORIES//,/ }; do
  log "graspd: $c"
  "$TARGET/release/examples/register_peer" "$c" "$OUT" "${REPEATS:-5}" >&2 || { log "ERROR: register_peer $c failed"; exit 1; }
done
"$PY" "$ROOT/bench/register_peer.py" --dir "$OUT" "$@"
