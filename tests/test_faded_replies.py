"""Every reply form says when a frame was faded toward the input (`models.motion.novelty`): JSON
frame replies carry `faded`, a session opened with encoding "binary-faded" gets it as one more
float32 after the rotations, and a crowd opened with `faded` gets one float32 per character after
the frames. A real server on loopback, the committed LTI, a walk that crouches to pick something
up (content no model was trained on) beside a plain walk."""

from __future__ import annotations

import json

import numpy as np
import pytest
from websockets.sync.client import connect

from models.data import load_motion, select
from models.motion.bn_skeleton import HIPS
from models.motion.retarget import retarget
from models.registry import load_model
from models.settings import get_settings
from service import protocol as P

from .live_server import live_server, ws_url
from .pick_up import pick_up

FLOATS = 3 + 4 * 22  # a Bandai Namco frame


@pytest.fixture(scope="module")
def clips(index):
    """The crouching walk (up to the end of its crouch) and a plain walk of the same length."""
    made = pick_up(load_motion(select(index, dataset="xia", name="neutral_walk_01_000")[0]), walk_s=1.0)
    crouch = retarget(made.motion)
    n = int(made.down[1] * crouch.fps)
    walk = load_motion(select(index, dataset="bandai-namco-2", style="normal", content="walk", split="val")[0])
    assert walk.num_frames >= n
    return crouch.slice(0, n), walk.slice(0, n)


@pytest.fixture(scope="module")
def server():
    models = {"lti": load_model(get_settings().weights_dir, "lti")}
    core = {"lti": load_model(get_settings().weights_dir, "lti", core_only=True)}
    with live_server(models, core_models=core, idle_timeout_s=30) as (base, _app):
        yield base


def _payload(motion, t: int) -> np.ndarray:
    return np.concatenate([motion.translations[t, HIPS], motion.rotations[t].ravel()]).astype("<f4")


def _session(base: str, motion, encoding: str, pipeline: str = "full") -> list:
    """Each reply to the clip's frames, sent in binary, answered in `encoding`."""
    start = {"type": "start", "model": "lti", "pipeline": pipeline, "style": "elderly", "encoding": encoding}
    replies = []
    with connect(ws_url(base)) as ws:
        ws.send(json.dumps(start))
        assert json.loads(ws.recv(timeout=30))["type"] == "started"
        for t in range(motion.num_frames):
            ws.send(P.BINARY_HEADER.pack(t, P.KIND_FRAME, 0) + _payload(motion, t).tobytes())
            reply = ws.recv(timeout=30)
            replies.append(json.loads(reply) if isinstance(reply, str) else reply)
    return replies


def test_a_binary_faded_session_gets_what_a_json_one_gets(server, clips):
    crouch, _ = clips
    wanted = np.array([r["faded"] for r in _session(server, crouch, "json")])
    plain = _session(server, crouch, "binary")
    tailed = _session(server, crouch, "binary-faded")
    assert wanted.max() > 0.9 and wanted[:10].max() == 0.0  # it faded on the crouch, not on the walk before it
    for a, b in zip(plain, tailed, strict=True):
        assert len(a) == P.binary_frame_size(22) and len(b) == len(a) + 4
        assert a == b[:-4]  # the frame itself is the same
    got = np.array([np.frombuffer(b, "<f4")[-1] for b in tailed])
    np.testing.assert_allclose(got, wanted, atol=1e-3)  # JSON rounds it to 3 decimals
    core = _session(server, crouch, "binary-faded", pipeline="core")
    assert all(np.frombuffer(b, "<f4")[-1] == 0.0 for b in core)  # the method alone never fades


def test_a_crowd_opened_with_faded_gets_each_characters(server, clips):
    crouch, walk = clips
    wanted = np.array([r["faded"] for r in _session(server, crouch, "json")])
    chars = [{"id": 7, "model": "lti", "style": "elderly"}, {"id": 3, "model": "lti", "style": "elderly"}]
    got = []
    with connect(ws_url(server)) as ws:
        ws.send(json.dumps({"type": "crowd", "characters": chars, "faded": True}))
        assert json.loads(ws.recv(timeout=30))["type"] == "crowd_started"
        ids = np.array([7, 3], "<u4")
        for t in range(crouch.num_frames):
            ws.send(P.encode_tick(t, ids, np.concatenate([_payload(crouch, t), _payload(walk, t)])))
            seq, _, got_ids, floats = P.decode_tick(ws.recv(timeout=30))
            assert seq == t and got_ids == ids.tobytes() and len(floats) == 2 * FLOATS + 2
            got.append(floats[-2:])
    got = np.array(got)
    np.testing.assert_allclose(got[:, 0], wanted, atol=1e-3)  # the crouching character's, as in its session
    assert got[:, 1].max() < 0.05  # the walking one's


def test_the_sdk_says_how_far_each_frame_faded(server, clips):
    from clients.sdk import Client

    crouch, _ = clips
    wanted = np.array([r["faded"] for r in _session(server, crouch, "json")])
    with Client(server).session("lti", "elderly") as session:
        got = np.array(
            [session.stylise(crouch.translations[t, HIPS], crouch.rotations[t]).faded for t in range(len(wanted))]
        )
    np.testing.assert_allclose(got, wanted, atol=1e-3)


def test_an_sdk_crowd_says_how_far_each_characters_frame_faded(server, clips):
    from clients.sdk import Character, Client

    crouch, walk = clips
    wanted = np.array([r["faded"] for r in _session(server, crouch, "json")])
    got = []
    with Client(server).crowd([Character(7, "lti", "elderly"), Character(3, "lti", "elderly")]) as crowd:
        for t in range(crouch.num_frames):
            roots = np.stack([crouch.translations[t, HIPS], walk.translations[t, HIPS]])
            frames = crowd.tick([7, 3], roots, np.stack([crouch.rotations[t], walk.rotations[t]]))
            assert len(frames.payload) == 2 * FLOATS  # the flags are not part of any frame
            got.append(frames.faded)
    got = np.array(got)
    np.testing.assert_allclose(got[:, 0], wanted, atol=1e-3)  # the crouching character's, as in its session
    assert got[:, 1].max() < 0.05  # the walking one's
