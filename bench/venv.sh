# Sourced by the peer benchmarks: sets up bench/.venv with numpy and the peers
# (pycpd==2.0.0, rustcpd==4.0.0 from PyPI) and sets ROOT, VENV, PY and log.
# A peer that cannot be installed is reported; its rows are then skipped.
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
