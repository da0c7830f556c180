#!/usr/bin/env bash
# Creates .venv with the service, training and test dependencies (torch 2.13.0, the CPU wheel).
set -euo pipefail
cd "$(dirname "$0")/.."
python3.11 -m venv .venv 2>/dev/null || python3 -m venv .venv
. .venv/bin/activate
python -m pip install -q --upgrade pip
python -m pip install -q "torch==2.13.0"
python -m pip install -q -e ".[service,training,test]"
