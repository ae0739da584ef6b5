#!/usr/bin/env bash
# Validates the deployment files offline: every manifest in deploy/k8s against the Kubernetes
# JSON schemas (strict, Kubernetes 1.27 and the newest bundled), the ServiceMonitor against
# deploy/schemas/, cross-references (selectors, ports, probes, drain vs grace period, HPA metric
# vs prometheus-adapter rule, ConfigMap TOML keys), deploy/compose.yaml, and a negative
# self-test (broken manifests must be rejected). Needs only PyPI: the schemas ship inside the
# kubernetes-validate package, installed into .venv-deploy (created on first run, ~110 MB,
# refreshed when deploy/requirements-validate.txt changes).
#   bash deploy/validate.sh            PYTHON=python3.12 bash deploy/validate.sh
# Ends with `validate: N passed, M failed`; exit status 1 on any failure.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${MPIFLOW_DEPLOY_VENV:-.venv-deploy}
REQ=deploy/requirements-validate.txt
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
exec "$VENV/bin/python" deploy/validate_manifests.py "$@"
