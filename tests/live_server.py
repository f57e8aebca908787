"""A real uvicorn server on a loopback port, in a background thread, for service tests."""

from __future__ import annotations

import threading
from contextlib import contextmanager

import uvicorn

from clients.loadtest import free_port, wait_ready
from service.app import create_app
from service.settings import ServiceSettings
from service.transport import uvicorn_config


@contextmanager
def live_server(models: dict, port: int | None = None, uvicorn_options: dict | None = None, **overrides):
    """Serve `models` on `port` (default: a free one; a fixed one lets a test restart the server
    where its clients expect it); `overrides` are settings, `uvicorn_options` uvicorn's own."""
    port = port or free_port()
    settings = ServiceSettings(port=port, **overrides)
    app = create_app(settings, models=models)
    server = uvicorn.Server(
        uvicorn_config(app, settings, host="127.0.0.1", log_level="warning", **(uvicorn_options or {}))
    )
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    base = f"http://127.0.0.1:{port}"
    wait_ready(base, lambda: thread.is_alive(), timeout=300)  # a fresh clone compiles every numba kernel first
    try:
        yield base, app
    finally:
        server.should_exit = True
        thread.join(timeout=10)
