"""Graceful drain on SIGTERM: new sessions are refused, every session is snapshotted and closed
with 1012 and its resume token, the process exits within `drain_timeout_s`, and the SDK carries
on by itself on another replica with the output of an uninterrupted run."""

from __future__ import annotations

import gc
import json
import signal
import threading
import time
from contextlib import contextmanager

import httpx
import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from clients.loadtest import free_port, wait_ready
from clients.sdk import Character, Client
from models.registry import load_models
from models.settings import get_settings
from service.app import create_app
from service.server import DrainingServer
from service.settings import ServiceSettings
from service.transport import uvicorn_config

from .cluster import READY_TIMEOUT_S, nginx, redis_server, replicas, require
from .test_replicas import FRAMES, KILL_AFTER, stream
from .waiting import wait_until


@contextmanager
def draining_server(**overrides):
    """A `DrainingServer` in a thread; the test sends it SIGTERM through `handle_exit`."""
    port = free_port()
    settings = ServiceSettings(port=port, **overrides)
    app = create_app(settings, models=load_models(get_settings().weights_dir))
    server = DrainingServer(
        uvicorn_config(app, settings, host="127.0.0.1", log_level="warning", timeout_graceful_shutdown=1),
        app,
        settings.drain_timeout_s,
    )
    thread = threading.Thread(target=server.run, daemon=True)
    gc.unfreeze()  # what an earlier server here froze: the startup's freeze is seen afresh
    thread.start()
    base = f"http://127.0.0.1:{port}"
    wait_ready(base, thread.is_alive, timeout=READY_TIMEOUT_S)
    try:
        yield base, server, thread
    finally:
        server.should_exit = server.force_exit = True
        thread.join(timeout=10)
        gc.unfreeze()  # this test process's heap goes back to the collector


def start(ws, **fields) -> dict:
    ws.send(json.dumps({"type": "start", "model": "lti", "style": "elderly", "encoding": "json", **fields}))
    return json.loads(ws.recv(timeout=10))


def send_frame(ws, seq: int, root, rot) -> dict:
    ws.send(json.dumps({"type": "frame", "seq": seq, "root": root.tolist(), "rotations": rot.tolist()}))
    while True:
        reply = json.loads(ws.recv(timeout=10))
        if reply["type"] == "frame":
            return reply


def test_the_server_freezes_its_startup_heap_out_of_the_garbage_collector():
    """Models, torch and numba stay for the process's life: full collections must not walk them
    (100-130 ms pauses under a 2,000-character crowd before)."""
    with draining_server():
        wait_until(lambda: gc.get_freeze_count() > 10_000, timeout=30, what="the startup heap frozen")


def test_sigterm_refuses_new_sessions_closes_open_ones_with_1012_and_exits_in_time(bn_walk):
    """The store is down here, so the drain waits out its flush and the window can be seen:
    readyz 503, new sessions refused; then the open session is closed with 1012 anyway."""
    root, rot = bn_walk.translations[:10, 1], bn_walk.rotations[:10]
    drain_timeout = 3.0
    with (
        draining_server(session_store=f"redis://127.0.0.1:{free_port()}/0", drain_timeout_s=drain_timeout) as (
            base,
            server,
            thread,
        ),
        connect(base.replace("http", "ws") + "/v1/stream") as ws,
    ):
        token = start(ws)["resume_token"]
        for t in range(10):
            send_frame(ws, t, root[t], rot[t])
        sigterm_at = time.monotonic()
        server.handle_exit(signal.SIGTERM, None)
        wait_until(lambda: httpx.get(f"{base}/readyz").status_code == 503, "readyz to turn 503 on SIGTERM")
        ready = httpx.get(f"{base}/readyz")
        assert (ready.status_code, ready.json()["status"]) == (503, "draining")
        with connect(base.replace("http", "ws") + "/v1/stream") as late:
            refused = start(late)
            assert refused["code"] == "draining"
            with pytest.raises(ConnectionClosed) as closed:
                late.recv(timeout=5)
            assert closed.value.rcvd.code == 1012
        with pytest.raises(ConnectionClosed) as closed:
            while True:
                ws.recv(timeout=drain_timeout)
        assert closed.value.rcvd.code == 1012 and token in closed.value.rcvd.reason
        thread.join(timeout=drain_timeout + 2)
        assert not thread.is_alive()
        assert time.monotonic() - sigterm_at < drain_timeout + 1


def test_a_drained_session_continues_on_the_other_replica_unchanged(tmp_path, bn_walk):
    """Real processes: SIGTERM to the replica holding an SDK session mid-stream; it exits in
    time and the session goes on, through nginx, on the other replica."""
    require("redis-server", "nginx")
    root, rot = bn_walk.translations[:FRAMES, 1], bn_walk.rotations[:FRAMES]
    drain_timeout = 5.0
    with (
        redis_server(tmp_path) as store,
        replicas(tmp_path, 2, session_store=store, drain_timeout_s=drain_timeout) as servers,
        nginx(tmp_path, [s.port for s in servers]) as lb,
    ):
        want, _, _ = stream(lb, root, rot)
        drained: dict = {}

        def sigterm_the_holder(t: int) -> None:
            if t + 1 == KILL_AFTER:
                holder = next(s for s in servers if s.metric("stylestream_active_sessions") == 1)
                drained.update(replica=holder, at=time.monotonic())
                holder.signal(signal.SIGTERM)
                watcher = threading.Thread(
                    target=lambda: (holder.proc.wait(), drained.update(exited=time.monotonic())), daemon=True
                )
                drained["watcher"] = watcher
                watcher.start()

        got, _, reconnects = stream(lb, root, rot, on_reply=sigterm_the_holder)
        holder = drained["replica"]
        holder.proc.wait(timeout=drain_timeout + 5)
        drained["watcher"].join(timeout=10)  # it notes the time
        took = drained["exited"] - drained["at"]
        survivor = next(s for s in servers if s is not holder)
        print(f"\ndrained replica exited {took:.2f} s after SIGTERM (code {holder.proc.returncode})")
        assert took < drain_timeout + 1
        assert holder.proc.returncode in (0, -signal.SIGTERM)  # uvicorn re-raises the signal it handled
        assert reconnects[-1] == 1
        assert survivor.metric("stylestream_sessions_resumed_total") == 1
        np.testing.assert_allclose(got, want, atol=1e-4)


def test_a_drained_crowd_continues_on_another_server_unchanged(tmp_path, bn_walk):
    """SIGTERM to the server holding a crowd after 10 ticks: it stores every character and closes
    with 1012; a crowd on another server sharing the store picks them up by their resume tokens,
    and the replies go on as an uninterrupted crowd's, bit for bit."""
    require("redis-server")
    chars = [Character(0, "lti", "elderly"), Character(1, "erd", "feminine"), Character(2, "lpn", "exhausted")]
    ticks = 24

    def run(crowd, ids, span) -> list[np.ndarray]:
        out = []
        for t in span:
            roots, rots = np.tile(bn_walk.translations[t, 1], (3, 1)), np.tile(bn_walk.rotations[t], (3, 1, 1))
            reply = crowd.tick(ids, roots, rots)
            out.append(np.concatenate([reply.frame(i)[1].ravel() for i in ids]))
        return out

    with (
        redis_server(tmp_path) as store,
        draining_server(session_store=store, drain_timeout_s=3.0) as (a, server_a, thread_a),
        draining_server(session_store=store) as (b, _, _),
    ):
        with Client(b, timeout=30).crowd(chars, fps=30) as whole:
            want = run(whole, [0, 1, 2], range(ticks))
        crowd = Client(a, timeout=30).crowd(chars, fps=30)
        run(crowd, [0, 1, 2], range(10))
        tokens = crowd.resume_tokens
        server_a.handle_exit(signal.SIGTERM, None)
        with pytest.raises(ConnectionClosed) as closed:
            crowd.io.ws.recv(timeout=10)
        assert closed.value.rcvd.code == 1012 and "resume tokens" in closed.value.rcvd.reason
        thread_a.join(timeout=10)
        again = [Character.resuming(i, chars[i].model, tokens[i]) for i in range(3)]
        with Client(b, timeout=30).crowd(again, fps=30) as resumed:
            assert resumed.errors == [] and resumed.resumed == {0: 9, 1: 9, 2: 9}
            got = run(resumed, [0, 1, 2], range(10, ticks))
    for t, (g, w) in enumerate(zip(got, want[10:], strict=True)):
        assert np.array_equal(g, w), t
