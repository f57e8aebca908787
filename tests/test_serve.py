"""`stylestream serve` starts a real server process that answers on loopback."""

import os
import subprocess
import sys

import httpx

from clients.loadtest import free_port, wait_ready


def test_serve_starts_and_answers_health_and_models():
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "clients.cli", "serve", "--port", str(port), "--log-level", "warning"],
                            env={**os.environ}, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        base = f"http://127.0.0.1:{port}"
        wait_ready(base, lambda: proc.poll() is None)
        assert httpx.get(f"{base}/healthz").json() == {"status": "ok"}
        models = httpx.get(f"{base}/v1/models").json()
        assert isinstance(models, list)
        for entry in models:
            assert entry["styles"], entry
        assert httpx.get(f"{base}/docs").status_code == 200
    finally:
        proc.terminate()
        proc.wait(timeout=20)


def test_cli_help_is_readable():
    out = subprocess.run([sys.executable, "-m", "clients.cli", "--help"], capture_output=True, text=True, check=True).stdout
    for command in ("serve", "data", "render", "retarget"):
        assert command in out
