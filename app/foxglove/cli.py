"""`vlmap foxglove` (the live view, `app.foxglove.live`) and `vlmap record` (a session's MCAP recording,
optionally drawn top-down to a PNG: `app.foxglove.preview`)."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Any


def _api_key(path: str | None) -> str | None:
    """The API key in the file, if one was named."""
    from app.client import read_api_key

    return None if path is None else read_api_key(Path(path))


def _common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--url", default="http://127.0.0.1:8000", help="the VL-Map service")
    parser.add_argument("--api-key-file", help="a file holding the API key (a viewer's key suffices)")


def add_parser(sub: Any) -> None:
    live = sub.add_parser("foxglove", help="serve the sessions live to Foxglove (its WebSocket protocol)")
    _common(live)
    which = live.add_mutually_exclusive_group()
    which.add_argument("--session", help="one session (default: every session the key may read)")
    which.add_argument("--robot", help="the sessions of one robot")
    live.add_argument("--host", default="127.0.0.1", help="address to serve on (default: loopback only)")
    live.add_argument("--port", type=int, default=8765, help="WebSocket port (Foxglove's default 8765)")
    live.set_defaults(func=serve_live)

    record = sub.add_parser("record", help="download a session's recording as MCAP (opens in Foxglove)")
    _common(record)
    record.add_argument("--session", required=True)
    record.add_argument("--out", required=True, type=Path, help="the .mcap file to write")
    record.add_argument(
        "--png", type=Path, help="also draw the last frame top-down to this PNG (needs requirements-dev.lock)"
    )
    record.set_defaults(func=record_session)


def serve_live(args: argparse.Namespace) -> int:
    from app.client import VLMapClient
    from app.foxglove.live import LiveServer

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    with VLMapClient(args.url, api_key=_api_key(args.api_key_file)) as client:
        server = LiveServer(
            client, session_id=args.session, robot_id=args.robot, host=args.host, port=args.port
        )
        print(f"Foxglove: open ws://{args.host}:{server.port} (Open connection > Foxglove WebSocket)")
        try:
            server.run()
        except KeyboardInterrupt:
            pass
        finally:
            server.stop()
    return 0


def record_session(args: argparse.Namespace) -> int:
    from app.client import VLMapClient

    with VLMapClient(args.url, api_key=_api_key(args.api_key_file)) as client:
        data = client.get_recording_mcap(args.session)
    args.out.write_bytes(data)
    print(f"wrote {args.out} ({len(data):,} bytes)")
    if args.png is not None:
        try:
            from app.foxglove.preview import render_png
        except ModuleNotFoundError as exc:
            print(f"--png needs {exc.name} (pip install -r requirements-dev.lock)", file=sys.stderr)
            return 2
        render_png(args.out, args.png)
        print(f"wrote {args.png}")
    return 0
