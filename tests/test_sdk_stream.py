"""The SDK's streaming beyond one frame at a time, against a real server: pipelined sends (replies
in order, equal to the one-in-flight outputs, also across a dropped connection), and coming back
after a server restart: with backoff for longer than the old SDK's 1.4 s, then a fresh session with
the same settings when the restarted server no longer knows the token, reported to the caller; or
a typed error at the caller's deadline."""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from contextlib import contextmanager

import numpy as np
import pytest

from clients.loadtest import free_port
from clients.sdk import AsyncClient, Client, ConnectionLost, Reconnect, StyledFrame
from models.registry import load_models
from models.settings import get_settings

from .live_server import live_server
from .waiting import wait_until

N = 48
STYLE_AT = 20  # a style change among pipelined frames


@pytest.fixture(scope="module")
def models():
    return {"lti": load_models(get_settings().weights_dir)["lti"]}


@pytest.fixture(scope="module")
def base(models):
    with live_server(models) as (url, _):
        yield url


@pytest.fixture(scope="module")
def clip(bn_walk):
    return bn_walk.translations[:N, 1].copy(), bn_walk.rotations[:N].copy()


def lockstep(base: str, root, rot) -> np.ndarray:
    with Client(base).session(model="lti", style="elderly") as session:
        out = []
        for t in range(len(root)):
            if t == STYLE_AT:
                session.set_style("exhausted", transition_frames=10)
            out.append(session.stylise(root[t], rot[t]).rotations)
    return np.array(out)


def test_pipelined_replies_come_in_order_and_equal_one_in_flight(base, clip):
    root, rot = clip
    want = lockstep(base, root, rot)
    got: list[StyledFrame] = []
    with Client(base).session(model="lti", style="elderly", max_in_flight=4) as session:
        for t in range(N):
            if t == STYLE_AT:  # waits for its acknowledgement; frame replies meanwhile are kept for us
                assert session.set_style("exhausted", transition_frames=10)["type"] == "style_set"
            assert session.send(root[t], rot[t]) == t
            assert session.in_flight <= 4 + len(got) + 1
            got += session.poll()  # whatever has arrived, without waiting
        while session.in_flight:
            got.append(session.receive())
    assert [f.seq for f in got] == list(range(N)) and all(f.dropped == 0 for f in got)
    np.testing.assert_array_equal(np.array([f.rotations for f in got]), want)


def test_asyncio_pipelining_gives_the_same_frames(base, clip):
    root, rot = clip
    want = lockstep(base, root, rot)

    async def run() -> list[StyledFrame]:
        async with AsyncClient(base) as client, client.session(model="lti", style="elderly", max_in_flight=3) as s:
            got = []
            for t in range(N):
                if t == STYLE_AT:
                    await s.set_style("exhausted", transition_frames=10)
                await s.send(root[t], rot[t])
                got += await s.poll()
            while s.in_flight:
                got.append(await s.receive())
            return got

    got = asyncio.run(run())
    assert [f.seq for f in got] == list(range(N))
    np.testing.assert_array_equal(np.array([f.rotations for f in got]), want)


def test_a_pipelined_session_resumes_exactly_after_its_connection_drops(base, clip):
    """The socket closes with frames in flight: the resume replays what the server's state lacks;
    every reply that arrives equals the uninterrupted run's, and the replies that went with the
    connection are reported (their frames are in the restored state)."""
    root, rot = clip
    want = lockstep(base, root, rot)
    events: list[Reconnect] = []
    got: dict[int, np.ndarray] = {}
    with Client(base).session(model="lti", style="elderly", max_in_flight=6, on_reconnect=events.append) as session:
        for t in range(N):
            if t == STYLE_AT:
                session.set_style("exhausted", transition_frames=10)
            session.send(root[t], rot[t])
            if t == 30:
                assert session.in_flight > 0
                session.ws.close()  # the connection drops with frames in flight
            for f in session.poll():
                got[f.seq] = f.rotations
        while session.in_flight:
            f = session.receive()
            got[f.seq] = f.rotations
    assert [e.kind for e in events] == ["resumed"] and session.reconnects == 1
    lost = set(events[0].lost)
    assert not lost & set(got) and lost | set(got) == set(range(N)), (sorted(got), lost)
    for seq, rotations in got.items():
        np.testing.assert_allclose(rotations, want[seq], atol=1e-6)


@contextmanager
def sdk_log():
    """The SDK's log records (its reconnect attempts), from any thread."""
    records: list[logging.LogRecord] = []
    handler = logging.Handler()
    handler.emit = records.append  # type: ignore[method-assign]
    logger = logging.getLogger("clients.sdk")
    level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        yield records
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)


def test_after_a_restart_a_session_keeps_trying_then_opens_a_fresh_one_with_its_settings(models, clip):
    """The server goes away for longer than the old SDK's 1.4 s give-up and comes back without the
    session (in-memory store): the pending frame is answered by a fresh session in the current
    style (`exhausted`, set after the start), and the caller is told."""
    root, rot = clip
    port = free_port()
    events: list[Reconnect] = []
    with live_server(models, port=port) as (base, _):
        session = Client(base, reconnect_timeout=120).session(model="lti", style="elderly", on_reconnect=events.append)
        session.set_style("exhausted")
        for t in range(10):
            session.stylise(root[t], rot[t])
    result: dict = {}
    waiter = threading.Thread(target=lambda: result.update(frame=session.stylise(root[10], rot[10])), daemon=True)
    with sdk_log() as records:
        waiter.start()  # finds the server gone and keeps trying
        # at least 7 failed attempts: the backoff pauses before them add up to more than 1.5 s
        wait_until(
            lambda: sum("reconnect attempt" in r.getMessage() for r in records) >= 7,
            "seven failed reconnect attempts",
            timeout=60,
        )
        with live_server(models, port=port) as (base, _):
            waiter.join(timeout=60)
            assert not waiter.is_alive()
            with Client(base).session(model="lti", style="exhausted") as fresh:
                want = fresh.stylise(root[10], rot[10])
            after = session.stylise(root[11], rot[11])
            session.close()
    frame = result["frame"]
    assert [e.kind for e in events] == ["new_session"] and session.new_sessions == 1 and session.reconnects == 0
    assert events[0].attempts >= 8 and events[0].seconds > 1.4 and events[0].last_seq is None
    assert frame.seq == 10 and after.seq == 11
    np.testing.assert_allclose(frame.rotations, want.rotations, atol=1e-6)


def test_a_session_gives_up_at_its_reconnect_deadline_with_a_typed_error(models, clip):
    root, rot = clip
    with live_server(models) as (base, _):
        session = Client(base, reconnect_timeout=0.5).session(model="lti", style="elderly")
        session.stylise(root[0], rot[0])
    t0 = time.monotonic()
    with pytest.raises(ConnectionLost, match="within 0.5 s"):
        session.stylise(root[1], rot[1])
    assert time.monotonic() - t0 < 5
    assert isinstance(ConnectionLost("x"), ConnectionError)  # caught as the built-in too

    async def run(url: str) -> None:
        async with AsyncClient(url, reconnect_timeout=0.5) as client:
            s = await client.session(model="lti", style="elderly").open()
            await s.stylise(root[0], rot[0])
            stop.set()
            assert await asyncio.to_thread(stopped.wait, 60)  # the loop runs on: the server's close is answered
            with pytest.raises(ConnectionLost):
                await s.stylise(root[1], rot[1])

    stop, stopped = threading.Event(), threading.Event()

    def serve(ready: dict) -> None:
        with live_server(models) as (url, _):
            ready["url"] = url
            stop.wait(60)
        stopped.set()

    ready: dict = {}
    threading.Thread(target=serve, args=(ready,), daemon=True).start()
    wait_until(lambda: "url" in ready, "the server", 120)
    asyncio.run(run(ready["url"]))
