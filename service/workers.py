"""Several server processes on one port (`stylestream serve --workers N`, `STYLESTREAM_WORKERS`).

One Python process saturates one core with its event loop, so more cores need more processes.
Each worker binds the port itself with SO_REUSEPORT: the kernel spreads new connections evenly
over the workers' listening sockets (by address hash), with no accept lock and no proxy hop.
Each worker is a whole server: its own models, batchers, metrics and drain. A session lives in
the worker its connection landed on, so a resumed connection lands on any worker: resume works
only with a shared session store, and the settings refuse `workers > 1` with the in-memory one.

The supervisor does nothing on the frame path: it starts the workers (spawned, so none inherits
another's threads), forwards SIGTERM/SIGINT so each drains its own sessions, and replaces a
worker that dies on its own. It also gives the workers one folder for prometheus_client's
multiprocess mode, so `/metrics` on any worker sums all of them (`service.metrics`).
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import shutil
import signal
import socket
import sys
import tempfile
import time
from multiprocessing.connection import wait
from types import FrameType

from .metrics import MULTIPROC_ENV
from .settings import ServiceSettings

log = logging.getLogger("uvicorn.error")
STARTUP_S = 120.0  # a worker that dies sooner than this after its start is not replaced


def reuse_port_socket(host: str, port: int) -> socket.socket:
    """A listening-ready TCP socket bound with SO_REUSEPORT, so every worker can bind the port."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
    sock.bind((host, port))
    sock.set_inheritable(True)
    return sock


def _worker(settings: ServiceSettings, log_level: str) -> None:
    from .server import serve_once

    serve_once(settings, log_level, sockets=[reuse_port_socket(settings.host, settings.port)])


def serve_workers(settings: ServiceSettings, log_level: str = "info") -> None:
    """Run `settings.workers` servers on one port until SIGTERM/SIGINT, then wait for their drains."""
    logging.basicConfig(level=log_level.upper(), format="%(levelname)s:     %(message)s")
    own_folder = not os.environ.get(MULTIPROC_ENV)  # an operator's own folder is theirs to keep
    if own_folder:
        os.environ[MULTIPROC_ENV] = tempfile.mkdtemp(prefix="stylestream-metrics-")  # spawned workers inherit it
    try:
        _supervise(settings, log_level)
    finally:
        if own_folder:
            shutil.rmtree(os.environ.pop(MULTIPROC_ENV), ignore_errors=True)


def _supervise(settings: ServiceSettings, log_level: str) -> None:
    from prometheus_client import multiprocess

    ctx = mp.get_context("spawn")
    stopping = False
    started: dict[mp.process.BaseProcess, float] = {}

    def start() -> mp.process.BaseProcess:
        proc = ctx.Process(target=_worker, args=(settings, log_level), name="stylestream-worker")
        proc.start()
        started[proc] = time.monotonic()
        return proc

    def stop(sig: int, frame: FrameType | None) -> None:
        nonlocal stopping
        stopping = True
        for proc in workers:
            if proc.is_alive():
                proc.terminate()  # SIGTERM: the worker drains its sessions, then exits

    exit_code = 0
    workers = [start() for _ in range(settings.workers)]
    log.info(
        "supervising %d workers on %s:%d (pids %s)",
        len(workers),
        settings.host,
        settings.port,
        ", ".join(str(p.pid) for p in workers),
    )
    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    while workers:
        wait([p.sentinel for p in workers])
        for proc in [p for p in workers if not p.is_alive()]:
            workers.remove(proc)
            multiprocess.mark_process_dead(proc.pid)  # its live gauges (open sessions) stop counting
            if stopping:
                continue
            if time.monotonic() - started.pop(proc) < STARTUP_S:  # it never came up (port taken, bad model): no loop
                log.error("worker %d exited with %s while starting: stopping", proc.pid, proc.exitcode)
                stop(signal.SIGTERM, None)
                exit_code = 1
                continue
            log.error("worker %d exited with %s: starting a replacement", proc.pid, proc.exitcode)
            workers.append(start())
    sys.exit(exit_code)
