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
# Two workers, each test file whole on one (its module fixtures, an MLflow server or a trained job, built once), the
# longest files first (tests/conftest.py): 610-627 s for a clean clone on two cores against 1,114 s in one process
# (2026-12-07; three workers were slower). TEST_WORKERS=0: one process.
workers=(-n "${TEST_WORKERS:-2}" --dist loadfile --no-loadscope-reorder)
if ! python -c "import xdist" 2>/dev/null; then
  echo "test.sh: pytest-xdist is missing from .venv (set up before it was needed): one process;" \
    "'bash scripts/setup.sh' installs it" >&2
  workers=()
fi
python -m pytest -q -p no:cacheprovider "${workers[@]}" "$@"
