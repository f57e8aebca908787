"""The SDK's protocol core against a scripted server, for the cases a real server produces only by
chance: replies lost with a connection, frames dropped by backpressure, an error answering one of
several pipelined frames, a `style_deleted` notice, a control message the snapshot already holds.
The core is I/O-free (`clients.sdk_session`), so a fake `perform` plays the server."""

from __future__ import annotations

import json
from collections import deque
from collections.abc import Callable

import numpy as np
import pytest

from clients.sdk_io import Close, Connect, Disconnected, Recv, RecvTimeout, Send, Sleep, run_sync
from clients.sdk_session import CALL, QUEUE, Entry, SessionCore, _result
from clients.sdk_types import FrameDropped, ServerError
from clients.sdk_wire import HEADER, StartSettings, pack, style_message

JOINTS = 22
ROOT, ROT = np.zeros(3), np.tile([0.0, 0.0, 0.0, 1.0], (JOINTS, 1))


def reply(seq: int, dropped: int = 0) -> bytes:
    return HEADER.pack(seq, 1, dropped) + np.full(3 + 4 * JOINTS, seq, "<f4").tobytes()


def started(last_seq: int | None = None, **extra) -> str:
    return json.dumps(
        {
            "type": "started",
            "session_id": "s",
            "resume_token": "tok",
            "joints": ["j"] * JOINTS,
            "last_seq": last_seq,
            **extra,
        }
    )


class FakeServer:
    """Answers each message the core sends with what `answer(server, message)` returns; a `cut`
    connection fails the next receive once its queued replies are read."""

    def __init__(self, answer: Callable[[FakeServer, dict | int], list]) -> None:
        self.answer, self.replies, self.cut, self.starts = answer, deque(), False, []

    def perform(self, op):
        if isinstance(op, Connect):
            self.cut = False
            return None
        if isinstance(op, Send):
            message = HEADER.unpack_from(op.data)[0] if isinstance(op.data, bytes) else json.loads(op.data)
            if isinstance(message, dict) and message["type"] == "start":
                self.starts.append(message)
            self.replies.extend(self.answer(self, message))
            return None
        if isinstance(op, Recv):
            if self.replies:
                return self.replies.popleft()
            if self.cut:
                raise Disconnected(1006)
            raise RecvTimeout()
        assert isinstance(op, Close | Sleep)
        return None


def core(server: FakeServer, window: int = 4) -> SessionCore:
    c = SessionCore(
        "ws://fake/v1/stream",
        StartSettings("lti", "elderly"),
        timeout=1.0,
        reconnect_timeout=1.0,
        max_in_flight=window,
        on_reconnect=None,
    )
    run_sync(c.open(), server)
    return c


def test_replies_lost_with_the_connection_are_reported_and_the_saved_one_handed_over():
    """Frames 0-3 are pipelined; the server processes all four but only frame 0's reply arrives
    before the connection goes. The resumed state is at frame 3 (its reply saved with it): frames
    1 and 2 are reported lost, 3 comes from the snapshot, and nothing is sent again."""

    def answer(server, message):
        if isinstance(message, dict):
            if message.get("resume_token"):
                return [started(3, last_frame={"seq": 3, "root": [3.0] * 3, "rotations": [[3.0] * 4] * JOINTS})]
            return [started()]
        if message == 3:
            server.cut = True
        return [reply(0)] if message == 0 else []

    server = FakeServer(answer)
    c = core(server)
    for _ in range(4):
        run_sync(c.send(ROOT, ROT), server)
    got = [run_sync(c.receive(1.0), server) for _ in range(2)]
    assert [f.seq for f in got] == [0, 3] and got[1].rotations[0, 0] == 3.0
    assert c.last_reconnect is not None and c.last_reconnect.lost == (1, 2) and c.last_reconnect.replayed == 0
    assert c.in_flight() == 0


def test_frames_dropped_by_backpressure_are_skipped_in_order_and_fail_a_call_waiting_on_one():
    """The server drops frame 1 (queue full) and says so on frame 2's reply. A call's frame can be
    dropped only when frames sent after it overtake it (concurrent asyncio tasks on one session):
    the call then gets a typed error rather than waiting for a reply that never comes."""

    def answer(server, message):
        if isinstance(message, dict):
            return [started()]
        return {0: [reply(0)], 1: [], 2: [reply(2, dropped=1)], 3: [], 4: [reply(4, dropped=1)]}[message]

    server = FakeServer(answer)
    c = core(server)
    for _ in range(3):
        run_sync(c.send(ROOT, ROT), server)
    got = [run_sync(c.receive(1.0), server) for _ in range(2)]
    assert [(f.seq, f.dropped) for f in got] == [(0, 0), (2, 1)]

    call = c._submit(Entry(3, pack(3, ROOT, ROT), CALL))
    c._submit(Entry(4, pack(4, ROOT, ROT), QUEUE))
    run_sync(c._pump(lambda: call.outcome is not None, None), server)
    with pytest.raises(FrameDropped):
        _result(call)
    assert run_sync(c.receive(1.0), server).seq == 4


def test_an_error_for_one_pipelined_frame_is_raised_in_its_place():
    """Bad frames are refused at once, so frame 1's error overtakes frame 0's reply; the caller
    still meets them in send order."""

    def answer(server, message):
        if isinstance(message, dict):
            return [started()]
        if message == 1:
            return [json.dumps({"type": "error", "code": "bad_frame", "message": "NaN", "seq": 1}), reply(0)]
        return [] if message == 0 else [reply(message)]

    server = FakeServer(answer)
    c = core(server, window=3)
    for _ in range(3):
        run_sync(c.send(ROOT, ROT), server)
    assert run_sync(c.receive(1.0), server).seq == 0
    with pytest.raises(ServerError) as err:
        run_sync(c.receive(1.0), server)
    assert (err.value.code, err.value.seq) == ("bad_frame", 1)
    assert run_sync(c.receive(1.0), server).seq == 2


def test_a_style_deleted_notice_rides_on_its_frame_instead_of_costing_the_reply():
    def answer(server, message):
        if isinstance(message, dict):
            return [started()]
        return [
            json.dumps({"type": "error", "code": "style_deleted", "message": "gone", "seq": message}),
            reply(message),
        ]

    server = FakeServer(answer)
    c = core(server)
    frame = run_sync(c.stylise(ROOT, ROT), server)
    assert frame.seq == 0 and [n.code for n in frame.notices] == ["style_deleted"]


def test_a_control_message_the_restored_snapshot_holds_is_answered_from_it():
    """set_style follows pipelined frame 0 and precedes frame 1; the server processed all three but
    the connection went before any reply. Resumed at frame 1, the style change is in the state:
    the call returns, frame 0 is lost, frame 1 is the snapshot's saved reply."""

    def answer(server, message):
        if isinstance(message, dict):
            if message["type"] == "start":
                saved = {"seq": 1, "root": [1.0] * 3, "rotations": [[1.0] * 4] * JOINTS}
                return [started(1, last_frame=saved)] if message.get("resume_token") else [started()]
            return []
        if message == 1:
            server.cut = True
        return []

    server = FakeServer(answer)
    c = core(server)

    def steps():
        yield from c.send(ROOT, ROT)
        style = c._submit(Entry(None, style_message("exhausted", None, 1.0, 0), CALL, "style_set"))  # as a task would
        yield from c.send(ROOT, ROT)
        frame = yield from c.receive(1.0)
        return frame, _result(style)

    frame, ack = run_sync(steps(), server)
    assert ack == {"type": "style_set", "restored": True}
    assert frame.seq == 1 and c.last_reconnect.lost == (0,)
    assert c.pending == deque() and len(server.starts) == 2


def test_poll_never_waits_on_a_lost_connection_the_next_receive_reconnects():
    """A game loop's poll returns at once when the connection has gone; the next call that waits
    (here receive) resumes the session and replays the unanswered frame."""

    def answer(server, message):
        if isinstance(message, dict):
            return [started()]
        if len(server.starts) == 1:
            server.cut = True  # the first connection dies with frame 0 unanswered
            return []
        return [reply(message)]

    server = FakeServer(answer)
    c = core(server)
    run_sync(c.send(ROOT, ROT), server)
    assert run_sync(c.poll(), server) == [] and len(server.starts) == 1  # no reconnect inside poll
    assert run_sync(c.receive(1.0), server).seq == 0
    assert len(server.starts) == 2 and c.last_reconnect.kind == "resumed" and c.last_reconnect.replayed == 1
