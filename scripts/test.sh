#!/usr/bin/env bash
# The test command: lint, the import contract (service never imports torch/mlflow/training), all tests.
set -euo pipefail
cd "$(dirname "$0")/.."
. .venv/bin/activate
: "${WEARMOCAP_DATA_DIR:?set WEARMOCAP_DATA_DIR to the data folder (the one with index.csv)}"
ruff check service training tests benchmarks
lint-imports
python -m pytest -q -p no:cacheprovider "$@"
