"""A real uvicorn server on a loopback port, in a background thread, for service tests."""

from __future__ import annotations

import socket
import threading
import time
from contextlib import contextmanager

import httpx
import uvicorn

from service.app import create_app
from service.settings import ServiceSettings


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_ready(base: str, alive, timeout: float = 60.0) -> None:
    """Poll /readyz until the server answers 200; fail early if it died."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            if httpx.get(f"{base}/readyz", timeout=1).status_code == 200:
                return
        except httpx.TransportError:
            pass
        if not alive():
            raise RuntimeError("server exited before it became ready")
        if time.monotonic() > deadline:
            raise RuntimeError(f"server not ready after {timeout:.0f} s")
        time.sleep(0.05)


@contextmanager
def live_server(models: dict, **overrides):
    port = free_port()
    settings = ServiceSettings(port=port, **overrides)
    app = create_app(settings, models=models)
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning",
                                           ws_max_size=4 * settings.max_message_bytes, ws_per_message_deflate=False))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    base = f"http://127.0.0.1:{port}"
    wait_ready(base, lambda: thread.is_alive())
    try:
        yield base, app
    finally:
        server.should_exit = True
        thread.join(timeout=10)
