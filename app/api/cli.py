"""`vlmap serve` and `vlmap openapi`."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

log = logging.getLogger("vlmap.serve")


def add_parser(sub: argparse._SubParsersAction) -> None:
    serve = sub.add_parser("serve", help="run the HTTP service")
    serve.add_argument("--host", default=None, help="bind address (default: settings, 127.0.0.1)")
    serve.add_argument("--port", type=int, default=None, help="port (default: settings, 8000)")
    serve.set_defaults(func=serve_command)

    spec = sub.add_parser("openapi", help="write the OpenAPI contract (sorted keys)")
    spec.add_argument("--out", type=Path, default=None, help="file to write (default: stdout)")
    spec.set_defaults(func=openapi_command)


def serve_command(args: argparse.Namespace) -> int:
    import uvicorn

    from app.api.app import create_app
    from app.api.observability import configure_logging
    from app.settings import get_settings

    settings = get_settings()
    host = args.host or settings.host
    port = args.port or settings.port
    configure_logging(settings.log_level, settings.log_json)
    log.info("starting", extra={"host": host, "port": port, "grounder": settings.grounder})
    uvicorn.run(create_app(settings), host=host, port=port, log_config=None, access_log=False)
    return 0


def openapi_spec() -> str:
    """The committed contract: the app's OpenAPI document as sorted, indented JSON."""
    from app.api.app import create_app

    return json.dumps(create_app().openapi(), sort_keys=True, indent=2) + "\n"


def openapi_command(args: argparse.Namespace) -> int:
    text = openapi_spec()
    if args.out is None:
        sys.stdout.write(text)
    else:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text, encoding="utf-8")
        print(f"wrote {args.out}")
    return 0
