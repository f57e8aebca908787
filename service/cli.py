"""`stylestream serve`: the service's own subcommand, added to the one `stylestream` command line
(`clients/cli.py`). It lives with the server; the server's packages are imported only when it runs."""

from __future__ import annotations

import argparse
import sys


def add_serve_command(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("serve", help="start the HTTP/WebSocket service")
    p.add_argument("--host", help="interface to bind (default 127.0.0.1, or STYLESTREAM_HOST)")
    p.add_argument("--port", type=int, help="port (default 8000, or STYLESTREAM_PORT)")
    p.add_argument(
        "--workers",
        type=int,
        help="server processes on the port (default 1, or STYLESTREAM_WORKERS); "
        "more than 1 needs STYLESTREAM_SESSION_STORE=redis://...",
    )
    p.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"])
    p.set_defaults(func=serve_command)


def serve_command(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from .server import serve
    from .settings import ServiceSettings

    given = {"host": args.host, "port": args.port, "workers": args.workers}
    try:
        settings = ServiceSettings(**{k: v for k, v in given.items() if v is not None})
    except ValidationError as exc:  # e.g. workers > 1 with the in-memory session store: say why, no traceback
        print(f"stylestream serve: {exc.errors()[0]['msg']}", file=sys.stderr)
        return 2
    serve(settings, log_level=args.log_level)  # SIGTERM drains the sessions (service/server.py)
    return 0
