"""A bad rig or a failure inside a connection costs that connection alone, and always says so.

A live server with LTI: a rig with a 1e308 OFFSET is a typed error in a session's `start`, in a
crowd's `join` (that character alone; the crowd goes on) and from `POST /v1/skeletons` (422, not
500); an exception inside a session's or a crowd's processor ends that connection with a typed
`internal` error, close 1011 and a log line, where it used to hang for ever with nothing logged;
a neighbour's session streams on through all of it."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import httpx
import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from models.registry import load_models
from models.settings import get_settings
from service import crowd as crowd_module
from service import protocol as P
from service import sessions as sessions_module

from .live_server import live_server, ws_url
from .test_rig_limits import chain, with_offsets

MIXAMO = (Path(__file__).parent / "fixtures" / "rigs" / "mixamo.bvh").read_text()
BAD = with_offsets(MIXAMO.split("MOTION")[0] + "MOTION\n", r"Spine$", "1e308 0 0")


@pytest.fixture(scope="module")
def models():
    return {"lti": load_models(get_settings().weights_dir)["lti"]}


@pytest.fixture(scope="module")
def server(models):
    with live_server(models, idle_timeout_s=30) as (base, app):
        yield base, app


@pytest.fixture(scope="module")
def style(models) -> str:
    return models["lti"].styles()[0]


def rest_frame(seq: int, joints: int = 22) -> bytes:
    rot = np.tile([0.0, 0.0, 0.0, 1.0], (joints, 1))
    payload = np.concatenate([[0.0, 90.0, 0.0], rot.ravel()]).astype("<f4")
    return P.BINARY_HEADER.pack(seq, P.KIND_FRAME, 0) + payload.tobytes()


def neighbour_answers(base: str, style: str) -> None:
    """A session of its own streams: whatever happened elsewhere did not touch it."""
    with connect(ws_url(base)) as ws:
        ws.send(json.dumps({"type": "start", "model": "lti", "style": style, "encoding": "binary"}))
        assert json.loads(ws.recv(timeout=30))["type"] == "started"
        for seq in range(3):
            ws.send(rest_frame(seq))
            assert isinstance(ws.recv(timeout=30), bytes)


def closed_with(ws, timeout: float = 30) -> int | None:
    """Read until the server closes; its close code."""
    with pytest.raises(ConnectionClosed) as closed:
        while True:
            ws.recv(timeout=timeout)
    return closed.value.rcvd.code if closed.value.rcvd else None


def test_a_session_start_with_a_non_finite_rig_is_a_typed_error(server, style):
    base, _ = server
    with connect(ws_url(base)) as ws:
        ws.send(json.dumps({"type": "start", "model": "lti", "style": style, "bvh_header": BAD}))
        reply = json.loads(ws.recv(timeout=30))
        assert (reply["type"], reply["code"]) == ("error", "bad_skeleton") and reply["message"].startswith("bad_offset")
        assert closed_with(ws) == 1008
    neighbour_answers(base, style)


def test_a_crowd_join_with_a_bad_rig_refuses_that_character_alone(server, style):
    base, _ = server
    with connect(ws_url(base)) as ws:
        ws.send(json.dumps({"type": "crowd", "characters": [{"id": 1, "model": "lti", "style": style}]}))
        assert json.loads(ws.recv(timeout=30))["type"] == "crowd_started"
        ws.send(
            json.dumps(
                {
                    "type": "join",
                    "characters": [
                        {"id": 2, "model": "lti", "style": style, "bvh_header": BAD},
                        {"id": 3, "model": "lti", "style": style, "bvh_header": chain(100)},
                        {"id": 4, "model": "lti", "style": style},
                    ],
                }
            )
        )
        joined = json.loads(ws.recv(timeout=30))
        assert joined["type"] == "joined" and [c["id"] for c in joined["characters"]] == [4]
        kinds = {e["id"]: (e["code"], e["message"].split(":", 1)[0]) for e in joined["errors"]}
        assert kinds == {2: ("bad_skeleton", "bad_offset"), 3: ("bad_skeleton", "rig_too_deep")}
        ids = np.array([1, 4], "<u4")  # the crowd goes on with the characters that joined
        payload = np.tile(np.frombuffer(rest_frame(0)[P.BINARY_HEADER.size :], "<f4"), 2)
        ws.send(P.encode_tick(0, ids, payload))
        seq, _, got, _ = P.decode_tick(ws.recv(timeout=30))
        assert seq == 0 and got == ids.tobytes()


@pytest.mark.parametrize(
    ("header", "kind"),
    [
        (BAD, "bad_offset"),
        (chain(100), "rig_too_deep"),
        (MIXAMO.replace("mixamorig:Hips", "H" * 300, 1), "bad_joint_name"),
    ],
)
def test_post_skeletons_answers_a_bad_rig_with_a_typed_422(server, header, kind):
    base, _ = server
    for preview in ("false", "true"):
        r = httpx.post(f"{base}/v1/skeletons?preview={preview}", json={"bvh_header": header}, timeout=60)
        assert r.status_code == 422 and r.json()["code"] == kind, r.text


def test_a_failing_crowd_processor_ends_the_crowd_with_a_typed_error(server, style, monkeypatch, caplog):
    """An exception the processor does not expect (here: in a reset) closes the crowd with
    `internal` and 1011 and logs it; before, the processor died silently and the client waited
    for ever."""
    base, _ = server

    def broken(self, rows):
        raise RuntimeError("injected failure")

    monkeypatch.setattr(crowd_module.Troupe, "reset", broken)
    with caplog.at_level(logging.ERROR), connect(ws_url(base)) as ws:
        ws.send(json.dumps({"type": "crowd", "characters": [{"id": 1, "model": "lti", "style": style}]}))
        assert json.loads(ws.recv(timeout=30))["type"] == "crowd_started"
        ws.send(json.dumps({"type": "reset", "characters": [1]}))
        reply = json.loads(ws.recv(timeout=30))
        assert (reply["type"], reply["code"]) == ("error", "internal"), reply
        assert closed_with(ws) == 1011
    assert any("processor failed" in r.getMessage() and r.exc_info for r in caplog.records)
    monkeypatch.undo()
    neighbour_answers(base, style)


def test_a_failing_session_processor_ends_the_session_with_a_typed_error(server, style, monkeypatch, caplog):
    base, app = server

    def broken(self):
        raise RuntimeError("injected failure")

    monkeypatch.setattr(sessions_module.Session, "reset", broken)
    with caplog.at_level(logging.ERROR), connect(ws_url(base)) as ws:
        ws.send(json.dumps({"type": "start", "model": "lti", "style": style, "encoding": "binary"}))
        started = json.loads(ws.recv(timeout=30))
        ws.send(rest_frame(0))
        assert isinstance(ws.recv(timeout=30), bytes)
        ws.send(json.dumps({"type": "reset"}))
        reply = json.loads(ws.recv(timeout=30))
        assert (reply["type"], reply["code"]) == ("error", "internal"), reply
        assert closed_with(ws) == 1011
    assert any("processor failed" in r.getMessage() and r.exc_info for r in caplog.records)
    monkeypatch.undo()
    with connect(ws_url(base)) as ws:  # the session was kept: it resumes where it was
        ws.send(json.dumps({"type": "start", "model": "lti", "resume_token": started["resume_token"]}))
        again = json.loads(ws.recv(timeout=30))
        assert again["type"] == "started" and again["last_seq"] == 0, again


def test_a_large_join_goes_in_parts_and_every_character_answers(server, style):
    """A join of 600 characters is added in parts, paced (other connections run between parts);
    a tick of all of them is answered for each, on every part's rows."""
    base, _ = server
    with connect(ws_url(base), max_size=None) as ws:
        ws.send(json.dumps({"type": "crowd", "characters": [{"id": 0, "model": "lti", "style": style}]}))
        assert json.loads(ws.recv(timeout=30))["type"] == "crowd_started"
        ws.send(
            json.dumps(
                {"type": "join", "characters": [{"id": i, "model": "lti", "style": style} for i in range(1, 601)]}
            )
        )
        joined = json.loads(ws.recv(timeout=60))
        assert len(joined["characters"]) == 600 and joined["errors"] == []
        ids = np.arange(601, dtype="<u4")[::-1].copy()
        payload = np.tile(np.frombuffer(rest_frame(0)[P.BINARY_HEADER.size :], "<f4"), 601)
        ws.send(P.encode_tick(0, ids, payload))
        seq, _, got, floats = P.decode_tick(ws.recv(timeout=60))
        assert seq == 0 and got == ids.tobytes() and len(floats) == 601 * 91
        rows = np.asarray(floats).reshape(601, 91)
        assert np.allclose(rows, rows[0])  # the same rest frame in: the same frame out, for every one
