"""``python -m service``: serve the shipped models with uvicorn."""

from __future__ import annotations

import argparse
import gc
import logging

import uvicorn

from service.app import create_app
from service.settings import get_settings
from service.websocket_protocol import WebSocketProtocol

GC_GEN0_THRESHOLD = 50_000


def main() -> None:
    parser = argparse.ArgumentParser(description="wearmocap inference service")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=8000)
    parser.add_argument(
        "--access-log", action="store_true", help="log every request (off: /metrics counts them, and it costs ~0.1 ms)"
    )
    parser.add_argument(
        "--ws-compression",
        action="store_true",
        help="permessage-deflate on WebSockets (off: it costs server CPU per message for small JSON results)",
    )
    parser.add_argument(
        "--gc-threshold",
        type=int,
        default=GC_GEN0_THRESHOLD,
        help="allocations between young-generation garbage collections (Python's default: 700)",
    )
    args = parser.parse_args()
    # A 256-window JSON body is ~33,000 lists and 200,000 floats. At Python's default threshold (700) the cyclic
    # collector runs dozens of times while one body is parsed and validated, and the older generations are
    # traversed again and again. 50,000 took 256-window JSON batches from ~990 to ~1,340 windows/s (median of 3
    # interleaved runs each on 2 cores; an uncommitted diagnostic, docs/benchmarks.md has the committed
    # figures). Only reference cycles wait longer; everything else is freed at once.
    gc.set_threshold(args.gc_threshold, 20, 100)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    settings = get_settings()
    uvicorn.run(
        create_app(settings),
        host=args.host,
        port=args.port,
        access_log=args.access_log,
        ws_per_message_deflate=args.ws_compression,
        ws=WebSocketProtocol,  # a client that stops answering pings (it stopped reading) is closed with 1008
        ws_ping_interval=settings.ws_ping_interval_s,
        ws_ping_timeout=settings.ws_ping_timeout_s,
    )


if __name__ == "__main__":
    main()
