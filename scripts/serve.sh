#!/usr/bin/env bash
# The main job: the service with the shipped models (onnx_models/) on http://127.0.0.1:8000, and the
# MLflow UI of the local tracking store (./mlflow.db) on http://127.0.0.1:5000. Ctrl-C or SIGTERM stops both,
# with every process they started; a port already in use is named before anything starts.
set -euo pipefail
cd "$(dirname "$0")/.."
[ -f .venv/.setup-complete ] || bash scripts/setup.sh  # also redoes a set-up that stopped half-way
. .venv/bin/activate
host="${HOST:-127.0.0.1}" port="${PORT:-8000}" ui_port="${MLFLOW_PORT:-5000}"
for p in "$port" "$ui_port"; do
  if ! python - "$host" "$p" <<'EOF'
import socket, sys
s = socket.socket()
s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
try:
    s.bind((sys.argv[1], int(sys.argv[2])))
except OSError:
    sys.exit(1)
EOF
  then
    echo "serve.sh: port $p on $host is in use (an earlier serve.sh still running? 'ss -ltnp | grep :$p' names it);" \
      "set PORT or MLFLOW_PORT to use others" >&2
    exit 1
  fi
done
set -m  # each background job in its own process group, so that stopping it stops its children too
python -m training.cli ui --host "$host" --port "$ui_port" &
ui=$!
WEARMOCAP_UI_URL="http://$host:$ui_port" python -m service --host "$host" --port "$port" &
svc=$!
stop() {
  trap - INT TERM EXIT
  kill -TERM -- "-$svc" "-$ui" 2>/dev/null || true
  wait 2>/dev/null || true
}
trap 'stop; exit 130' INT
trap 'stop; exit 143' TERM
trap stop EXIT
wait -n "$svc" "$ui"
