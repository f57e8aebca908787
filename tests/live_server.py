"""A real uvicorn server on a loopback port, in a background thread, for service tests."""

from __future__ import annotations

import threading
from contextlib import contextmanager

import numpy as np
import uvicorn

from clients.loadtest import free_port, wait_ready
from models.interface import FrameBatch, style_vector
from service.app import create_app
from service.settings import ServiceSettings
from service.transport import uvicorn_config

# How long a test waits for an upload's answer: a clip is decoded and its style built at the
# background's low priority (`service.background`), which on a loaded machine waits long for a
# core (httpx's own 5 s default was not enough beside four busy processes)
UPLOAD_TIMEOUT_S = 120.0


@contextmanager
def live_server(
    models: dict,
    port: int | None = None,
    uvicorn_options: dict | None = None,
    core_models: dict | None = None,
    **overrides,
):
    """Serve `models` (and the cores in `core_models`, as their `core` pipelines) on `port`
    (default: a free one; a fixed one lets a test restart the server where its clients expect
    it); `overrides` are settings, `uvicorn_options` uvicorn's own."""
    port = port or free_port()
    settings = ServiceSettings(port=port, **overrides)
    app = create_app(settings, models=models, core_models=core_models)
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


def ws_url(base: str, path: str = "/v1/stream") -> str:
    return base.replace("http", "ws") + path


def offline(model, style_mix: dict, root: np.ndarray, rot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The model run alone, frame by frame, on a fresh state: what a session must reproduce."""
    state = model.init_state(1)
    w = style_vector(model, style_mix)[None]
    roots, rots = [], []
    for t in range(len(root)):
        out, state = model.step_batch(state, FrameBatch(root[t : t + 1], rot[t : t + 1]), w)
        roots.append(out.root[0])
        rots.append(out.rotations[0])
    return np.array(roots), np.array(rots)
