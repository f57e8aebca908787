"""`stylestream serve --workers N`: N server processes on one port (SO_REUSEPORT).

Connections are spread over the workers, a session resumes on whichever worker its new
connection lands on (through the shared Redis store), `/metrics` on any worker counts every
worker's frames, SIGTERM drains every worker and the supervisor exits cleanly; with the
in-memory store more than one worker is refused."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import httpx
from websockets.sync.client import connect

from clients.soak import metric_values
from service import protocol as P

from .cluster import REPO, Replica, redis_server, require
from .waiting import wait_until

SESSIONS = 16  # all on one of two workers by chance: 2 / 2**16


def _workers(supervisor: int) -> list[int]:
    """Pids of the supervisor's worker processes (not multiprocessing's resource tracker)."""
    children = Path(f"/proc/{supervisor}/task/{supervisor}/children").read_text().split()
    return [int(p) for p in children if b"spawn_main" in Path(f"/proc/{p}/cmdline").read_bytes()]


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _stream(url: str, root, rot, resume_token: str | None = None) -> str:
    """Open (or resume) a binary LTI session, stylise 10 frames; returns its resume token."""
    with connect(url) as ws:
        ws.send(
            json.dumps(
                {
                    "type": "start",
                    "model": "lti",
                    "style": "elderly",
                    "encoding": "binary",
                    "resume_token": resume_token,
                }
            )
        )
        started = json.loads(ws.recv(timeout=30))
        assert started["type"] == "started", started
        seq0 = 0 if started["last_seq"] is None else started["last_seq"] + 1
        for t in range(seq0, seq0 + 10):
            ws.send(P.encode_binary(t, root[t], rot[t]))
            seq = int.from_bytes(ws.recv(timeout=30)[:4], "little")
            assert seq == t
        return started["resume_token"]


def _scrape(base: str) -> dict[str, float]:
    """/metrics over a fresh connection (any worker may answer), each name summed over its labels."""
    return metric_values(httpx.get(f"{base}/metrics", headers={"Connection": "close"}, timeout=10).text)


def test_more_than_one_worker_needs_a_shared_store():
    done = subprocess.run(
        [sys.executable, "-m", "clients.cli", "serve", "--workers", "2"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, "STYLESTREAM_SESSION_STORE": "memory"},
    )
    assert done.returncode == 2
    assert "shared session_store" in done.stderr


def test_two_workers_share_the_port_and_resume_each_others_sessions(tmp_path, bn_walk):
    require("redis-server")
    root, rot = bn_walk.translations[:, 1], bn_walk.rotations  # Hips translation, local quaternions
    with redis_server(tmp_path) as store:
        server = Replica(tmp_path, "workers", workers=2, session_store=store)
        try:
            server.wait_ready()
            workers = _workers(server.proc.pid)
            assert len(workers) == 2
            cpu0 = {p: _cpu_s(p) for p in workers}
            url = server.url.replace("http", "ws", 1) + "/v1/stream"
            tokens = [_stream(url, root, rot) for _ in range(SESSIONS)]
            assert all(_cpu_s(p) - cpu0[p] > 0.02 for p in workers), "a worker served no session"
            wait_until(
                lambda: _scrape(server.url)["stylestream_snapshots_total"] >= SESSIONS,
                "the snapshots of the closed sessions to reach the store",
            )
            for token in tokens:  # about half land on the other worker than the session's first
                _stream(url, root, rot, resume_token=token)
            wait_until(
                lambda: _scrape(server.url)["stylestream_active_sessions"] == 0,
                "the last sessions' closes to be counted",
            )
            for _ in range(8):  # scrapes land on both workers; each answers for all of them
                metrics = _scrape(server.url)  # only LTI sessions ran
                assert metrics["stylestream_frames_total"] == 2 * SESSIONS * 10
                assert metrics["stylestream_active_sessions"] == 0
            server.signal(signal.SIGTERM)
            assert server.proc.wait(timeout=60) == 0
            assert all(not Path(f"/proc/{p}").exists() for p in workers)
        finally:
            server.stop()
