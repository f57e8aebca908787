"""Probes are never limited: `/healthz` and `/readyz` answer at `max_connections` (uvicorn's cap
answered them 503, so an orchestrator would restart a healthy server for being busy), and
readiness says `full` while every connection or session is taken."""

from __future__ import annotations

import json
import socket
from contextlib import ExitStack

import httpx
import pytest
from websockets.sync.client import connect

from models.registry import load_models
from models.settings import get_settings

from .live_server import live_server, ws_url
from .waiting import wait_until

MAX_CONNECTIONS = 6


@pytest.fixture(scope="module")
def server():
    models = {"lti": load_models(get_settings().weights_dir)["lti"]}
    with live_server(models, max_connections=MAX_CONNECTIONS, max_sessions=1) as (base, _app):
        yield base


def test_probes_answer_at_max_connections_and_readiness_says_full(server):
    port = int(server.rsplit(":", 1)[1])
    with ExitStack() as held:
        for _ in range(MAX_CONNECTIONS):  # open connections that send nothing (yet)
            held.enter_context(socket.create_connection(("127.0.0.1", port)))
        wait_until(lambda: httpx.get(f"{server}/v1/models").status_code == 503, "the connection cap to be reached")
        health = httpx.get(f"{server}/healthz")
        assert (health.status_code, health.json()) == (200, {"status": "ok"})
        ready = httpx.get(f"{server}/readyz")
        assert (ready.status_code, ready.json()) == (503, {"status": "full"})
    wait_until(lambda: httpx.get(f"{server}/readyz").status_code == 200, "readiness once connections closed")
    assert httpx.get(f"{server}/v1/models").status_code == 200


def test_readiness_says_full_while_every_session_is_taken(server):
    with connect(ws_url(server)) as ws:
        ws.send(json.dumps({"type": "start", "model": "lti", "style": "elderly"}))
        assert json.loads(ws.recv(timeout=30))["type"] == "started"
        ready = httpx.get(f"{server}/readyz")
        assert (ready.status_code, ready.json()) == (503, {"status": "full"})
    wait_until(lambda: httpx.get(f"{server}/readyz").status_code == 200, "readiness once the session closed")
