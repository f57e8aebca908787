"""Log lines an operator can follow: every session line names its session and model, and what
comes every few seconds from machines (health probes, readiness checks, `/metrics` scrapes) and
uvicorn's per-socket open/close lines (the session lines say more) stay at debug; API tokens
given in a URL are written as `token=***`."""

from __future__ import annotations

import logging
import re
from collections.abc import MutableMapping
from typing import Any

PROBE_PATHS = frozenset({"/healthz", "/readyz", "/metrics"})
SOCKET_LINES = frozenset({"connection open", "connection closed"})
TOKEN_IN_QUERY = re.compile(r"([?&](?:token|access_token)=)[^&\s\"']*", re.IGNORECASE)


class SessionLog(logging.LoggerAdapter):
    """Prefixes `session=<id> model=<name>`, so one session's lines can be picked out of many."""

    def process(self, msg: Any, kwargs: MutableMapping[str, Any]) -> tuple[Any, MutableMapping[str, Any]]:
        extra = self.extra or {}
        return f"session={extra['session']} model={extra['model']} {msg}", kwargs


def session_log(logger: logging.Logger, session_id: str, model: str) -> SessionLog:
    return SessionLog(logger, {"session": session_id, "model": model})


def _routine(record: logging.LogRecord) -> bool:
    if record.name == "uvicorn.access" and isinstance(record.args, tuple) and len(record.args) >= 3:
        return str(record.args[2]).split("?", 1)[0] in PROBE_PATHS  # (client, method, path, version, status)
    if record.name == "uvicorn.error" and record.levelno == logging.INFO:
        message = record.getMessage()
        return message in SOCKET_LINES or ('"WebSocket ' in message and message.endswith("[accepted]"))
    return False


class RoutineAtDebug(logging.Filter):
    """Turns routine records into debug records: kept when the logger shows debug, else dropped."""

    def filter(self, record: logging.LogRecord) -> bool:
        if not _routine(record):
            return True
        record.levelno, record.levelname = logging.DEBUG, "DEBUG"
        return logging.getLogger(record.name).isEnabledFor(logging.DEBUG)


def redact(text: str) -> str:
    """`?token=secret` as `?token=***`: a browser's WebSocket cannot send an Authorization header,
    so the viewer puts its token in the URL, and access logs must not keep it."""
    return TOKEN_IN_QUERY.sub(r"\1***", text)


class RedactTokens(logging.Filter):
    """Tokens out of every record's arguments (uvicorn logs request paths with their query)."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.args, tuple):
            record.args = tuple(redact(a) if isinstance(a, str) else a for a in record.args)
        elif isinstance(record.msg, str):
            record.msg = redact(record.msg)
        return True


def configure_logging() -> None:
    """After `uvicorn.Config` has set its loggers up: routine lines at debug, and the service's own
    loggers (`service.*`: sessions, store, styles) written through uvicorn's handler at uvicorn's
    level, beside its lines (left alone, only their warnings reached Python's last-resort handler)."""
    for name in ("uvicorn.access", "uvicorn.error"):
        logger = logging.getLogger(name)
        for kind in (RedactTokens, RoutineAtDebug):
            if not any(isinstance(f, kind) for f in logger.filters):
                logger.addFilter(kind())
    service = logging.getLogger("service")
    service.setLevel(logging.getLogger("uvicorn.error").getEffectiveLevel())
    for handler in logging.getLogger("uvicorn").handlers:
        if handler not in service.handlers:
            service.addHandler(handler)
    service.propagate = False
