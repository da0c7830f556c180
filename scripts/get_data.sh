#!/usr/bin/env bash
# Rebuilds the data directory from its public origins with the repository's .venv (docs/data.md):
#   scripts/get_data.sh --dest DIR [--sources a,b] [--mirror URL] [--jobs N]
# Needs only the base install (numpy); rerun it to resume. Exit status 1 if a file failed (each is listed).
set -euo pipefail
repo="$(cd "$(dirname "$0")/.." && pwd)"
python="$repo/.venv/bin/python"
if [ ! -x "$python" ]; then
  echo "get_data: $python not found; run scripts/setup.sh first" >&2
  exit 1
fi
PYTHONPATH="$repo${PYTHONPATH:+:$PYTHONPATH}" exec "$python" -m training.data.get "$@"
