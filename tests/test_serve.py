"""`stylestream serve` starts a real server process that answers on loopback."""

import os
import subprocess
import sys

import httpx
import numpy as np

from clients.loadtest import free_port, wait_ready
from clients.sdk import Client


def test_serve_starts_and_answers_health_and_models(tmp_path):
    """Also its log at info: each session line names the session and model; the probes, the
    readiness polling and the scrapes are not there (debug)."""
    port = free_port()
    log = tmp_path / "serve.log"
    with log.open("w") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "clients.cli", "serve", "--port", str(port), "--log-level", "info"],
            env={**os.environ},
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    try:
        base = f"http://127.0.0.1:{port}"
        wait_ready(base, lambda: proc.poll() is None)
        assert httpx.get(f"{base}/healthz").json() == {"status": "ok"}
        models = httpx.get(f"{base}/v1/models").json()
        assert isinstance(models, list)
        for entry in models:
            assert entry["styles"], entry
        assert httpx.get(f"{base}/docs").status_code == 200
        assert httpx.get(f"{base}/metrics").status_code == 200
        with Client(base).session(model="lti", style="elderly") as session:
            session.stylise(np.zeros(3), np.tile([0.0, 0.0, 0.0, 1.0], (22, 1)))
            sid = session.session_id
    finally:
        proc.terminate()
        proc.wait(timeout=20)
    lines = log.read_text().splitlines()
    session_lines = [line for line in lines if sid in line]
    assert len(session_lines) == 2, lines[-20:]  # started, ended
    assert all(f"session={sid} model=lti" in line for line in session_lines)
    assert not [
        line for line in lines if any(p in line for p in ("/healthz", "/readyz", "/metrics", "connection open"))
    ]
    assert any("GET /v1/models" in line for line in lines)  # the rest of the access log stays


def test_cli_help_is_readable():
    out = subprocess.run(
        [sys.executable, "-m", "clients.cli", "--help"], capture_output=True, text=True, check=True
    ).stdout
    for command in ("serve", "data", "render", "retarget"):
        assert command in out


def test_a_serving_process_lets_the_event_loop_take_the_gil_back_sooner():
    """Background threads (style building, fine-tunes) would otherwise hold the GIL for Python's
    5 ms switch interval whenever the event loop wants it: each such wait a stream's late frame."""
    from service.server import tune_interpreter
    from service.settings import ServiceSettings

    before = sys.getswitchinterval()
    try:
        tune_interpreter(ServiceSettings())
        assert sys.getswitchinterval() == ServiceSettings().gil_switch_interval_s < before
        tune_interpreter(ServiceSettings(gil_switch_interval_s=0.002))
        assert sys.getswitchinterval() == 0.002
    finally:
        sys.setswitchinterval(before)
