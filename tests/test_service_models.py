"""Every committed model streams through a real session exactly as it runs alone."""

from __future__ import annotations

import json

import numpy as np
import pytest
from websockets.sync.client import connect

from models.interface import FrameBatch, style_vector
from models.registry import load_models
from models.settings import get_settings

from .live_server import live_server

MODELS = load_models(get_settings().weights_dir)


def test_the_committed_models_are_all_served():
    assert {"lti", "erd"} <= set(MODELS)


@pytest.mark.parametrize("name", sorted(MODELS))
def test_session_output_equals_the_model_alone(name, bn_walk):
    model = MODELS[name]
    style = "elderly" if "elderly" in model.styles() else model.styles()[0]
    m = bn_walk.slice(0, 45)
    root, rot = m.translations[:, 1], m.rotations
    state, w = model.init_state(1), style_vector(model, {style: 1.0})[None]
    want = []
    for t in range(len(root)):
        out, state = model.step_batch(state, FrameBatch(root[t : t + 1], rot[t : t + 1]), w)
        want.append(out.rotations[0])
    with live_server({name: model}) as (base, _):
        with connect(base.replace("http", "ws") + "/v1/stream") as ws:
            ws.send(json.dumps({"type": "start", "model": name, "style": style}))
            assert json.loads(ws.recv(timeout=10))["type"] == "started"
            got = []
            for t in range(len(root)):
                ws.send(json.dumps({"type": "frame", "seq": t, "root": root[t].tolist(), "rotations": rot[t].tolist()}))
                got.append(json.loads(ws.recv(timeout=10))["rotations"])
    np.testing.assert_allclose(np.array(got), np.array(want), atol=1e-6)
    assert np.isfinite(got).all()
