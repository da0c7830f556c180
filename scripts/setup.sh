#!/usr/bin/env bash
# Creates .venv with the service, training and test dependencies: Python 3.11 and torch 2.13.0, the CPU build.
#
# torch comes from PyTorch's CPU wheel index (https://download.pytorch.org/whl/cpu) when that index answers; a plain
# `pip install torch` elsewhere is the multi-GB CUDA build. Where the index cannot be reached (a closed network with
# its own package mirror), pip's configured indexes are used instead; TORCH_INDEX_URL overrides the choice.
# A set-up that stopped half-way (no .venv/.setup-complete) is started over, so that serve.sh never trusts it.
set -euo pipefail
cd "$(dirname "$0")/.."
done_marker=.venv/.setup-complete

if [ -d .venv ] && [ ! -f "$done_marker" ]; then
  echo "setup: .venv is from a set-up that did not finish; starting over"
  rm -rf .venv
fi
python=""
for candidate in python3.11 "$HOME/.pyenv/versions/3.11"*/bin/python3.11 python3; do
  if command -v "$candidate" >/dev/null 2>&1 \
    && "$candidate" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null; then
    python=$candidate
    break
  fi
done
if [ -z "$python" ]; then
  echo "setup: training needs Python 3.11 (torch 2.13.0's CPU wheel is tested here on 3.11); none found." >&2
  echo "       The service alone runs on Python 3.11-3.13: pip install '.[service]' (docs/service.md)." >&2
  exit 1
fi

echo "[1/3] virtual environment .venv ($("$python" --version))"
[ -d .venv ] || "$python" -m venv .venv
. .venv/bin/activate
python -m pip install -q --upgrade pip

torch_index="${TORCH_INDEX_URL-}"
if [ -z "${TORCH_INDEX_URL+set}" ] \
  && python -c 'import urllib.request; urllib.request.urlopen("https://download.pytorch.org/whl/cpu/torch/", timeout=5)' \
    2>/dev/null; then
  torch_index=https://download.pytorch.org/whl/cpu
fi
echo "[2/3] torch 2.13.0, CPU build (${torch_index:-from the configured pip indexes}; about 200 MB)"
python -m pip install --progress-bar on ${torch_index:+--index-url "$torch_index"} "torch==2.13.0"

echo "[3/3] the project with its service, training and test dependencies"
python -m pip install --progress-bar on -e ".[service,training,team,test]"
python -c "import fastapi, mlflow, onnxruntime, torch, uvicorn" \
  || { echo "setup: the installed packages do not import; see pip's messages above" >&2; exit 1; }
touch "$done_marker"
echo "setup: done. Start the service with scripts/serve.sh; run the tests with scripts/test.sh"
