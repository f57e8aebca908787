"""The direct frame path (`service.transport`, `service.stream`): a single-character session's
binary frames taken straight from the WebSocket protocol and answered from the batch step's
callback. It must answer exactly what the ASGI path answers, in the same order, whatever mix of
frames, style changes, resets and resumes comes, and keep what the ASGI path keeps (the idle
timeout sees its frames)."""

from __future__ import annotations

import json
import re
import socket
import time
from collections.abc import Callable

import httpx
import numpy as np
import pytest
from websockets.sync.client import connect

from models.registry import load_models
from models.settings import get_settings
from service import protocol as P
from service.transport import GuardedWebSocket

from .live_server import live_server, ws_url

N_FRAMES = 60


@pytest.fixture(scope="module")
def models():
    return load_models(get_settings().weights_dir)


@pytest.fixture(scope="module")
def served(models):
    """The same models served twice, (url, app) each: direct path on (the default) and off. A
    long session queue, so pipelined frames are never dropped (what is dropped depends on timing)."""
    with (
        live_server(models, session_queue=256) as direct,
        live_server(models, session_queue=256, direct_frames=False) as asgi,
    ):
        yield direct, asgi


@pytest.fixture(scope="module")
def servers(served):
    return tuple(base for base, _ in served)


@pytest.fixture(scope="module")
def clip(bn_walk):
    m = bn_walk.slice(0, N_FRAMES)
    return m.translations[:, 1].copy(), m.rotations.copy()


def direct_frames(base: str) -> float:
    text = httpx.get(f"{base}/metrics").text
    found = re.search(r'^stylestream_direct_frames_total\{model="lti"\} (\S+)$', text, re.M)
    return float(found.group(1)) if found else 0.0


def on_both(servers: tuple[str, str], session: Callable[[str], list]) -> list[tuple[list, float]]:
    """`session(url)`'s replies from the direct server, then the ASGI one, each with how many
    frames that server took by the direct path meanwhile."""
    out = []
    for base in servers:
        before = direct_frames(base)
        replies = session(base)
        out.append((replies, direct_frames(base) - before))
    return out


def open_session(ws, **fields) -> dict:
    ws.send(json.dumps({"type": "start", "model": "lti", "encoding": "binary", "fps": 60, **fields}))
    started = json.loads(ws.recv(timeout=30))
    assert started["type"] == "started", started
    return started


def reply(ws) -> bytes | dict:
    data = ws.recv(timeout=30)
    return data if isinstance(data, bytes) else json.loads(data)


def lockstep(ws, clip, frames: range, controls: dict[int, dict]) -> list:
    """Each frame sent after the previous reply; `controls[t]` sent (and answered) before frame t."""
    root, rot = clip
    replies = []
    for t in frames:
        if t in controls:
            ws.send(json.dumps(controls[t]))
            replies.append(reply(ws))
        ws.send(P.encode_binary(t, root[t], rot[t]))
        replies.append(reply(ws))
    return replies


def style_changes(models) -> dict[int, dict]:
    a, b = models["lti"].styles()[:2]
    return {
        20: {"type": "style", "style": b, "transition_frames": 12},
        40: {"type": "reset"},
        50: {"type": "style", "mix": {a: 0.5, b: 0.5}},
    }


def test_lockstep_binary_frames_all_go_direct_and_answer_as_the_asgi_path(servers, models, clip):
    """A client that waits for each reply: every frame is taken directly (the model at 30 fps
    under a 60 fps stream: half of them answered with the held output at once), style changes
    and a reset between them, a dropped connection resumed halfway; every reply byte for byte
    what the ASGI path sends."""
    style = models["lti"].styles()[0]
    controls = style_changes(models)

    def session(base: str) -> list:
        with connect(ws_url(base)) as ws:
            token = open_session(ws, style=style)["resume_token"]
            got = lockstep(ws, clip, range(0, 30), controls)
        with connect(ws_url(base)) as ws:
            assert open_session(ws, style=style, resume_token=token)["last_seq"] == 29
            return got + lockstep(ws, clip, range(30, N_FRAMES), controls)

    (direct, direct_count), (asgi, asgi_count) = on_both(servers, session)
    assert (direct_count, asgi_count) == (N_FRAMES, 0)
    assert len(direct) == N_FRAMES + len(controls) and direct == asgi
    frames = [r for r in direct if isinstance(r, bytes)]
    assert len(set(frames)) > N_FRAMES // 2  # the model moved (held frames repeat rotations, not roots)


def test_pipelined_frames_mixing_both_paths_answer_as_the_asgi_path(servers, models, clip):
    """Frames and controls sent without waiting: what arrives while a frame is in hand takes the
    ASGI path, the rest the direct one; the replies and their order are the same either way."""
    root, rot = clip
    style = models["lti"].styles()[0]
    controls = style_changes(models)

    def session(base: str) -> list:
        with connect(ws_url(base)) as ws:
            open_session(ws, style=style)
            for t in range(N_FRAMES):
                if t in controls:
                    ws.send(json.dumps(controls[t]))
                ws.send(P.encode_binary(t, root[t], rot[t]))
            return [reply(ws) for _ in range(N_FRAMES + len(controls))]

    (direct, direct_count), (asgi, asgi_count) = on_both(servers, session)
    assert direct_count >= 1 and asgi_count == 0
    assert direct == asgi
    seqs = [P.BINARY_HEADER.unpack_from(r)[0] for r in direct if isinstance(r, bytes)]
    assert seqs == list(range(N_FRAMES))


def test_a_session_fed_only_by_the_direct_path_is_not_idle(models, clip):
    """Its frames never reach the receive loop, whose idle timer must still see them."""
    root, rot = clip
    with live_server(models, idle_timeout_s=1.5) as (base, _), connect(ws_url(base)) as ws:
        open_session(ws, style=models["lti"].styles()[0])
        t, t0 = 0, time.monotonic()
        while time.monotonic() - t0 < 4.0:  # well past the 1.5 s timeout
            ws.send(P.encode_binary(t, root[t % N_FRAMES], rot[t % N_FRAMES]))
            answer = reply(ws)
            assert isinstance(answer, bytes), answer
            t += 1
            time.sleep(1 / 30)  # a 30 fps client
        ws.send(json.dumps({"type": "end"}))
        assert reply(ws)["type"] == "ended"


def test_a_failing_model_step_costs_its_frame_and_the_session_goes_on(served, clip, monkeypatch):
    """A step that raises answers its frame with a typed `internal` error, on either path, and
    the next frames are stylised as before."""

    def failing_on_the_marked_frame(step_batch):
        def step(state, frames, weights):
            if np.any(frames.root[:, 0] == 1234.0):
                raise RuntimeError("a model failure")
            return step_batch(state, frames, weights)

        return step

    root, rot = clip[0].copy(), clip[1]
    root[5, 0] = 1234.0
    answers = []
    for base, app in served:
        model = app.state.runtime.models["lti"]  # the server's own copy (its own style set)
        monkeypatch.setattr(model, "step_batch", failing_on_the_marked_frame(model.step_batch))
        with connect(ws_url(base)) as ws:
            open_session(ws, style=model.styles()[0], fps=30)  # every frame steps the model
            answers.append(lockstep(ws, (root, rot), range(10), {}))
    direct, asgi = answers
    assert direct == asgi
    assert direct[5]["type"] == "error" and (direct[5]["code"], direct[5]["seq"]) == ("internal", 5)
    assert all(isinstance(r, bytes) for i, r in enumerate(direct) if i != 5)


def test_a_client_that_stops_reading_gets_every_reply_in_order_or_is_told_it_was_dropped(servers, models, clip):
    """Thousands of frames sent before reading any reply: the socket fills, direct replies that
    cannot be written at once are sent the awaiting way, frames beyond the queue are dropped;
    every reply comes in order and replies + reported drops add up to what was sent."""
    root, rot = clip
    sent = 2000
    host, port = servers[0].removeprefix("http://").split(":")
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # a small window: the server's writes back up
    sock.connect((host, int(port)))
    with connect(ws_url(servers[0]), sock=sock, max_size=None) as ws:
        open_session(ws, style=models["lti"].styles()[0])
        for t in range(sent):
            ws.send(P.encode_binary(t, root[t % N_FRAMES], rot[t % N_FRAMES]))
            time.sleep(0.001)  # paced, so most frames find the session idle and take the direct path
        ws.send(json.dumps({"type": "end"}))
        seqs, dropped = [], 0
        while isinstance(answer := reply(ws), bytes):
            seq, _, was_dropped = P.BINARY_HEADER.unpack_from(answer)
            seqs.append(seq)
            dropped += was_dropped
        assert answer["type"] == "ended", answer
    assert seqs == sorted(seqs) and seqs[-1] == sent - 1
    assert len(seqs) + dropped == sent


def test_a_direct_reply_the_socket_cannot_take_at_once_is_sent_in_order_the_awaiting_way(
    servers, models, clip, monkeypatch
):
    """Every other direct reply refused by the transport (as when the peer's buffer is full):
    those go by a send task, and the stream is still byte for byte the ASGI path's."""
    write_binary = GuardedWebSocket.write_binary
    calls = []

    def refuse_every_other(self, data: bytes) -> bool:
        calls.append(len(calls) % 2 == 0)
        return calls[-1] and write_binary(self, data)

    monkeypatch.setattr(GuardedWebSocket, "write_binary", refuse_every_other)
    style = models["lti"].styles()[0]
    answers = []
    for base in servers:
        with connect(ws_url(base)) as ws:
            open_session(ws, style=style)
            answers.append(lockstep(ws, clip, range(N_FRAMES), style_changes(models)))
    assert answers[0] == answers[1]
    assert len(calls) == N_FRAMES and calls.count(False) == N_FRAMES // 2  # the ASGI server never calls it
