#!/usr/bin/env bash
# Creates (or refreshes) the project's Python environment in .venv and prints the exports the
# tests and the server need; installs the Python client (clients/python) too. Idempotent and quick
# when nothing changed.
#   eval "$(bash tools/setup_python.sh)"
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=.venv
REQ=tools/requirements-test.txt
PY=${PYTHON:-python3}
if [ ! -x "$VENV/bin/python" ]; then
  "$PY" -m venv "$VENV" >&2
fi
STAMP="$VENV/.requirements.sha256"
SUM=$(sha256sum "$REQ" | cut -d' ' -f1)
if [ ! -f "$STAMP" ] || [ "$(cat "$STAMP")" != "$SUM" ]; then
  "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check -r "$REQ" >&2
  echo "$SUM" > "$STAMP"
fi
# The Python client (clients/python, import name mpiflow), editable: the tests use the tree's code.
PKG=clients/python
PKG_STAMP="$VENV/.mpiflow-client.stamp"
PKG_SUM="$(sha256sum "$PKG/pyproject.toml" | cut -d' ' -f1) $PWD"
if [ ! -f "$PKG_STAMP" ] || [ "$(cat "$PKG_STAMP")" != "$PKG_SUM" ] \
  || ! "$VENV/bin/python" -c "import mpiflow" >/dev/null 2>&1; then
  "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check -e "$PKG" >&2
  echo "$PKG_SUM" > "$PKG_STAMP"
fi
ORT_LIB=$("$VENV/bin/python" - <<'PY'
import glob, os, onnxruntime
libs = sorted(glob.glob(os.path.join(os.path.dirname(onnxruntime.__file__), "capi", "libonnxruntime.so*")))
print(libs[-1] if libs else "")
PY
)
if [ -z "$ORT_LIB" ]; then
  echo "setup_python: the onnxruntime wheel has no libonnxruntime.so" >&2
  exit 1
fi
echo "export ORT_DYLIB_PATH='$ORT_LIB'"
echo "export MPIFLOW_PYTHON='$PWD/$VENV/bin/python'"
