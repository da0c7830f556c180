#!/usr/bin/env bash
# The main job: the service with the shipped models (onnx_models/) on http://127.0.0.1:8000, and the
# MLflow UI of the local tracking store (./mlflow.db) on http://127.0.0.1:5000. Ctrl-C stops both.
set -euo pipefail
cd "$(dirname "$0")/.."
[ -x .venv/bin/python ] || bash scripts/setup.sh
. .venv/bin/activate
python -m training.cli ui --port "${MLFLOW_PORT:-5000}" &
ui=$!
trap 'kill $ui 2>/dev/null' EXIT
python -m service --host "${HOST:-127.0.0.1}" --port "${PORT:-8000}"
