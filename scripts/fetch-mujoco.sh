#!/usr/bin/env bash
# Puts the MuJoCo C library that the sim crate links against into
# third_party/mujoco/lib/ (gitignored):
#
#   third_party/mujoco/lib/libmujoco.so.3.17.0
#   third_party/mujoco/lib/libmujoco.so -> libmujoco.so.3.17.0
#
# The library comes from the PyPI wheel mujoco==3.17.0 (the wheel carries the
# same shared library that DeepMind's release tarball does); only that one file
# is taken from it. The version is pinned together with the crate mujoco-rs
# 7.0.0, whose struct layouts are compiled for MuJoCo 3.17.0.
#
# Idempotent: when the library is already there it only checks the symlink
# and exits. Needs python3 with pip and unzip (or python3's zipfile), and
# network access to PyPI on the first run.
set -euo pipefail
cd "$(dirname "$0")/.."

VERSION=3.17.0
DIR=third_party/mujoco/lib
LIB="libmujoco.so.$VERSION"
PY="${PYTHON:-python3}"

if [ ! -s "$DIR/$LIB" ]; then
    mkdir -p "$DIR"
    TMP="$(mktemp -d)"
    trap 'rm -rf "$TMP"' EXIT
    echo "fetching mujoco==$VERSION from PyPI (wheel, for $LIB) ..." >&2
    # --only-binary: never build MuJoCo from an sdist; --no-deps: the wheel's
    # Python dependencies are not needed for the C library.
    "$PY" -m pip download -q "mujoco==$VERSION" --no-deps --only-binary=:all: -d "$TMP" >&2
    WHEEL="$(ls "$TMP"/mujoco-"$VERSION"-*.whl | head -n 1)"
    # Extract to a temporary name first so an interrupted run never leaves a
    # truncated library that the check above would take for a good one.
    "$PY" - "$WHEEL" "mujoco/$LIB" "$DIR/$LIB.partial" <<'EOF'
import shutil, sys, zipfile
wheel, member, dest = sys.argv[1:]
with zipfile.ZipFile(wheel) as z, z.open(member) as src, open(dest, "wb") as out:
    shutil.copyfileobj(src, out)
EOF
    mv "$DIR/$LIB.partial" "$DIR/$LIB"
fi

# The crate's build script links `-lmujoco`, which the linker resolves through
# the unversioned name.
if [ "$(readlink "$DIR/libmujoco.so" 2>/dev/null || true)" != "$LIB" ]; then
    ln -sfn "$LIB" "$DIR/libmujoco.so"
fi
echo "MuJoCo $VERSION: $(cd "$DIR" && pwd)/$LIB" >&2
