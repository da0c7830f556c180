#!/usr/bin/env bash
# The test command: lint, the import contract (service never imports torch/mlflow/training), all tests.
set -euo pipefail
cd "$(dirname "$0")/.."
. .venv/bin/activate
if [ -z "${WEARMOCAP_DATA_DIR:-}" ]; then
  echo "test.sh: WEARMOCAP_DATA_DIR is not set: the tests that read the data directory are skipped" \
    "(marker needs_data; docs/data.md says how to get it)" >&2
fi
ruff check service training tests benchmarks
lint-imports
python -m pytest -q -p no:cacheprovider "$@"
