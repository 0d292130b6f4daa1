"""`vlmap serve` and `vlmap openapi`."""

from __future__ import annotations

import argparse
import ipaddress
import json
import logging
import sys
from pathlib import Path

log = logging.getLogger("vlmap.serve")


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    serve = sub.add_parser("serve", help="run the HTTP service")
    serve.add_argument("--host", default=None, help="bind address (default: settings, 127.0.0.1)")
    serve.add_argument("--port", type=int, default=None, help="port (default: settings, 8000)")
    serve.add_argument(
        "--allow-open", action="store_true", help="serve without API keys on a non-loopback address"
    )
    serve.set_defaults(func=serve_command)

    keys = sub.add_parser("keys", help="API key management")
    keys_sub = keys.add_subparsers(dest="keys_command", required=True)
    new = keys_sub.add_parser("new", help="mint a key: prints the key once and the record for the key file")
    new.add_argument("--name", required=True)
    new.add_argument("--role", required=True, choices=["robot", "viewer", "admin"])
    new.add_argument("--robot-id", action="append", default=[], help="robot ids a robot key may act for")
    new.set_defaults(func=new_key_command)

    spec = sub.add_parser("openapi", help="write the OpenAPI contract (sorted keys)")
    spec.add_argument("--out", type=Path, default=None, help="file to write (default: stdout)")
    spec.set_defaults(func=openapi_command)


def serve_command(args: argparse.Namespace) -> int:
    import uvicorn

    from app.api.app import create_app
    from app.api.auth import KeyRing
    from app.api.observability import configure_logging
    from app.api.server import guarded_protocol
    from app.settings import get_settings

    settings = get_settings()
    host = args.host or settings.host
    port = args.port or settings.port
    configure_logging(settings.log_level, settings.log_json)
    keyring = KeyRing.load(settings.api_keys_file, settings.api_keys)
    if keyring.is_open:
        if not is_loopback(host) and not (args.allow_open or settings.allow_open):
            log.error(
                "refusing to serve %s without API keys: set VLMAP_API_KEYS_FILE (see `vlmap keys new`), "
                "or pass --allow-open / VLMAP_ALLOW_OPEN=true to run open on purpose",
                host,
            )
            return 2
        log.warning("no API keys configured: every request is accepted (fine on loopback for development)")
    log.info("starting", extra={"host": host, "port": port, "grounder": settings.grounder})

    def stop() -> None:  # a failed start-up: stop serving (exit 1 below), not answer "still loading" for ever
        server.should_exit = True

    app = create_app(settings, start_in_background=True, on_startup_failure=stop)
    server = uvicorn.Server(
        uvicorn.Config(
            app,
            host=host,
            port=port,
            log_config=None,
            access_log=False,
            http=guarded_protocol(settings.header_timeout_s, settings.max_header_bytes),
            limit_concurrency=settings.max_connections,
            timeout_keep_alive=settings.keep_alive_s,
        )
    )
    server.run()
    if not server.started:  # e.g. the port is taken: uvicorn.run's exit code for it
        return 3
    return 0 if app.state.services.startup_error is None else 1


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def new_key_command(args: argparse.Namespace) -> int:
    from app.api.auth import digest, new_key

    key = new_key()
    record = {"name": args.name, "role": args.role, "sha256": digest(key), "robot_ids": args.robot_id}
    print(f"key (shown once, give it to the client): {key}")
    print(f"record (add it to the keys file): {json.dumps(record)}")
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
