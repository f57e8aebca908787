"""Controller sessions: `control` ticks drive LPN-FiLM through the service exactly as the model
runs alone; a model that takes no control refuses them with a typed error and carries on."""

from __future__ import annotations

import json

import numpy as np
from websockets.sync.client import connect

from clients.sdk import Client
from models.interface import FrameBatch, style_vector
from models.registry import load_models
from models.settings import get_settings

from .live_server import live_server

MODELS = load_models(get_settings().weights_dir)
# walk forward, turn left while walking, run, stop: one tick per model frame (30 fps)
SCRIPT = (
    [((1.4, 0.0), 0.0, "walk")] * 30
    + [((1.4, 0.0), 0.8, "walk")] * 20
    + [((3.5, 0.0), 0.8, "run")] * 20
    + [((0.0, 0.0), 0.8, "walk")] * 20
)


def control_rows(script) -> np.ndarray:
    return np.array([[v[0], v[1], facing, 1.0 if gait == "run" else 0.0, 1.0] for v, facing, gait in script])


def test_lpn_is_served_as_a_controller():
    assert getattr(MODELS["lpn"], "controllable", False)
    with live_server({"lpn": MODELS["lpn"]}) as (base, _):
        info = {m.name: m for m in Client(base).models()}
    assert info["lpn"].controllable


def test_control_session_equals_the_model_driven_alone():
    model = MODELS["lpn"]
    style = "elderly"
    rows = control_rows(SCRIPT)
    rest = np.zeros((1, len(model.skeleton.names), 4))
    rest[..., 3] = 1.0
    state, w = model.init_state(1), style_vector(model, {style: 1.0})[None]
    want = []
    for row in rows:
        out, state = model.step_batch(state, FrameBatch(np.zeros((1, 3)), rest, control=row[None]), w)
        want.append(out.root[0])
    with live_server({"lpn": model}) as (base, _):
        with Client(base).session(model="lpn", style=style) as session:
            got = [session.control(v, facing, gait).root for v, facing, gait in SCRIPT]
    got, want = np.array(got), np.array(want)
    np.testing.assert_allclose(got, want, atol=1e-3)  # binary replies are float32
    # it walks: the root travels forward (+Z) first, then turns toward +X (facing 0.8 rad)
    assert want[29, 2] - want[0, 2] > 50.0
    assert want[69, 0] - want[49, 0] > 30.0


def test_a_model_without_control_refuses_it_and_the_session_goes_on(bn_walk):
    model = MODELS["lti"]
    m = bn_walk.slice(0, 3)
    with live_server({"lti": model}) as (base, _):
        with connect(base.replace("http", "ws") + "/v1/stream") as ws:
            ws.send(json.dumps({"type": "start", "model": "lti", "style": "elderly"}))
            assert json.loads(ws.recv(timeout=10))["type"] == "started"
            ws.send(json.dumps({"type": "control", "seq": 0, "velocity": [1.0, 0.0], "facing": 0.0}))
            error = json.loads(ws.recv(timeout=10))
            assert (error["type"], error["code"], error["seq"]) == ("error", "control_unsupported", 0)
            ws.send(
                json.dumps(
                    {
                        "type": "frame",
                        "seq": 1,
                        "root": m.translations[0, 1].tolist(),
                        "rotations": m.rotations[0].tolist(),
                    }
                )
            )
            assert json.loads(ws.recv(timeout=10))["type"] == "frame"


BAD_CONTROLS = [
    {"velocity": [1.0], "facing": 0.0},  # one component
    {"velocity": [40.0, 0.0], "facing": 0.0},  # faster than any sprint
    {"velocity": [1.0, 0.0], "facing": "north"},
    {"velocity": [1.0, 0.0], "facing": 0.0, "gait": "crawl"},
]


def test_malformed_control_is_a_typed_error_and_the_session_goes_on():
    with live_server({"lpn": MODELS["lpn"]}) as (base, _):
        with connect(base.replace("http", "ws") + "/v1/stream") as ws:
            ws.send(json.dumps({"type": "start", "model": "lpn", "style": "elderly"}))
            assert json.loads(ws.recv(timeout=10))["type"] == "started"
            for bad in BAD_CONTROLS:
                ws.send(json.dumps({"type": "control", "seq": 0, **bad}))
                error = json.loads(ws.recv(timeout=10))
                assert (error["type"], error["code"]) == ("error", "bad_message"), bad
            ws.send(json.dumps({"type": "control", "seq": 1, "velocity": [1.0, 0.0], "facing": 0.0}))
            assert json.loads(ws.recv(timeout=10))["seq"] == 1
