"""``python -m service``: serve the shipped models with uvicorn."""

from __future__ import annotations

import argparse
import logging

import uvicorn

from service.app import create_app


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
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    uvicorn.run(
        create_app(),
        host=args.host,
        port=args.port,
        access_log=args.access_log,
        ws_per_message_deflate=args.ws_compression,
    )


if __name__ == "__main__":
    main()
