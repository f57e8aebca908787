"""Real processes for the scale-out tests: redis-server, `stylestream serve` replicas and an nginx
load balancer, each on a free loopback port with its files in a temporary folder.

The server binaries come from Debian (`make servers` installs them); a test that needs a missing
one is skipped, saying which.
"""

from __future__ import annotations

import itertools
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest

from clients.loadtest import free_port, wait_ready
from clients.metrics_text import metric_values

REPO = Path(__file__).resolve().parents[1]
READY_TIMEOUT_S = 240.0


def require(*binaries: str) -> None:
    """Skip the calling test unless every binary is installed."""
    missing = [b for b in binaries if shutil.which(b) is None and not Path("/usr/sbin", b).exists()]
    if missing:
        pytest.skip(f"{', '.join(missing)} not installed (`make servers` installs them)")


def _binary(name: str) -> str:
    return shutil.which(name) or str(Path("/usr/sbin", name))


def _wait_port(port: int, alive, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if not alive():
            raise RuntimeError(f"process for port {port} exited")
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return
        except OSError:
            time.sleep(0.05)
    raise TimeoutError(f"nothing listens on port {port}")


def _start(args: list[str], **kwargs) -> subprocess.Popen:
    """A server process that leads its own process group, so `_stop` can end it together with
    whatever it forks (nginx workers, `--workers` children)."""
    return subprocess.Popen(args, start_new_session=True, **kwargs)


def _stop(proc: subprocess.Popen, graceful: bool = True, grace_s: float = 10.0) -> None:
    """SIGTERM the group leader so it stops its children itself (nginx's master stops its workers,
    which a SIGKILL of the master alone leaves running, listening on their port), then SIGKILL
    whatever of its process group is left; `graceful=False` goes straight to the SIGKILL."""
    if graceful and proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            pass
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:  # the group is gone already
        pass
    proc.wait(timeout=10)


@contextmanager
def redis_server(folder: Path):
    """A throwaway redis-server (no persistence); yields its URL."""
    port = free_port()
    proc = _start(
        [
            _binary("redis-server"),
            "--port",
            str(port),
            "--bind",
            "127.0.0.1",
            "--dir",
            str(folder),
            "--save",
            "",
            "--appendonly",
            "no",
            "--logfile",
            str(folder / "redis.log"),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.STDOUT,
    )
    try:
        _wait_port(port, lambda: proc.poll() is None)
        yield f"redis://127.0.0.1:{port}/0"
    finally:
        _stop(proc)


class Replica:
    """One `stylestream serve` process."""

    def __init__(self, folder: Path, name: str, **env: str) -> None:
        self.port, self.name = free_port(), name
        self.url = f"http://127.0.0.1:{self.port}"
        self.log = folder / f"{name}.log"
        environment = {**os.environ, **{f"STYLESTREAM_{k.upper()}": str(v) for k, v in env.items()}}
        self.proc = _start(
            [sys.executable, "-m", "clients.cli", "serve", "--port", str(self.port), "--log-level", "info"],
            cwd=REPO,
            env=environment,
            stdout=self.log.open("w"),
            stderr=subprocess.STDOUT,
        )

    def wait_ready(self) -> None:
        # generous: loading and warming the models (numba compiles) on a busy 2-core box
        wait_ready(self.url, lambda: self.proc.poll() is None, timeout=READY_TIMEOUT_S)

    def metric(self, name: str) -> float:
        """Sum of a metric's samples on /metrics (all label values)."""
        return metric_values(httpx.get(f"{self.url}/metrics", timeout=5).text).get(name, 0.0)

    def signal(self, sig: signal.Signals) -> None:
        self.proc.send_signal(sig)

    def stop(self) -> None:
        _stop(self.proc, graceful=False)  # a drain would only slow the teardown; its workers go with it


@contextmanager
def replicas(folder: Path, count: int, **env: str):
    started = [Replica(folder, f"replica{i}", **env) for i in range(count)]
    try:
        for r in started:  # started together, so their model loading overlaps
            r.wait_ready()
        yield started
    finally:
        for r in started:
            r.stop()


NGINX_CONF = """
worker_processes 1;
pid {folder}/nginx.pid;
error_log {folder}/nginx-error.log warn;
events {{ worker_connections 256; }}
http {{
    access_log off;
    # style uploads: kept in memory (the worker user may not write under the test's folder)
    client_max_body_size 17m;
    client_body_buffer_size 17m;
    client_body_temp_path {folder}/body;
    proxy_temp_path {folder}/proxy;
    fastcgi_temp_path {folder}/fastcgi;
    uwsgi_temp_path {folder}/uwsgi;
    scgi_temp_path {folder}/scgi;
    map $http_upgrade $connection_upgrade {{ default upgrade; '' close; }}
    upstream stylestream {{
{servers}
    }}
    server {{
        listen 127.0.0.1:{port};
        location / {{
            proxy_pass http://stylestream;
            proxy_http_version 1.1;
            proxy_set_header Upgrade $http_upgrade;
            proxy_set_header Connection $connection_upgrade;
            proxy_set_header Host $host;
            proxy_connect_timeout 1s;
            proxy_read_timeout 3600s;
            proxy_send_timeout 3600s;
            proxy_next_upstream error timeout;
        }}
    }}
}}
"""


@contextmanager
def nginx(folder: Path, upstream_ports: list[int]):
    """nginx in the foreground as a WebSocket-aware round-robin load balancer; yields its URL."""
    port = free_port()
    servers = "\n".join(f"        server 127.0.0.1:{p} max_fails=1 fail_timeout=5s;" for p in upstream_ports)
    with _nginx_running(folder, NGINX_CONF.format(folder=folder, port=port, servers=servers), port) as url:
        yield url


@contextmanager
def shipped_nginx(folder: Path, upstream_ports: list[int]):
    """nginx with the shipped configuration (docker/nginx.conf) as compose runs it, only its
    listening port, upstream addresses and writable paths moved into the test's folder."""
    port = free_port()
    conf = (Path(__file__).resolve().parents[1] / "docker" / "nginx.conf").read_text()
    conf = re.sub(
        r"server stylestream-\d+:8000",
        lambda m, ports=itertools.cycle(upstream_ports): f"server 127.0.0.1:{next(ports)}",
        conf,
    )
    conf = conf.replace("listen 8080;", f"listen 127.0.0.1:{port};").replace(
        "pid /tmp/nginx.pid;", f"pid {folder}/nginx.pid;"
    )
    conf = conf.replace("worker_processes auto;", "worker_processes 1;").replace(
        "access_log /dev/stdout;", "access_log off;"
    )
    temp = "".join(
        f"    {kind}_temp_path {folder}/{kind};\n" for kind in ("client_body", "proxy", "fastcgi", "uwsgi", "scgi")
    )
    conf = conf.replace("http {\n", "http {\n" + temp, 1)
    with _nginx_running(folder, conf, port) as url:
        yield url


@contextmanager
def _nginx_running(folder: Path, conf_text: str, port: int):
    conf = folder / "nginx.conf"
    conf.write_text(conf_text)
    proc = _start(
        [
            _binary("nginx"),
            "-p",
            str(folder),
            "-c",
            str(conf),
            "-e",
            str(folder / "nginx-error.log"),
            "-g",
            "daemon off;",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.STDOUT,
    )
    try:
        _wait_port(port, lambda: proc.poll() is None)
        yield f"http://127.0.0.1:{port}"
    finally:
        _stop(proc)
