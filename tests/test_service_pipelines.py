"""A session or crowd character may ask for a method's published core alone (`pipeline: core`):
its frames are the core's (`load(..., core_only=True)`) stepped offline, not the shipped
pipeline's; it resumes as a core session on both stores; a crowd mixes pipelines; and what the
core cannot do is a typed error."""

from __future__ import annotations

import json

import httpx
import numpy as np
import pytest
from websockets.sync.client import connect

from clients.sdk import Character, Client
from models.registry import load_models
from models.settings import get_settings
from service.sessions import Snapshot

from .clips import frames_json
from .cluster import redis_server, require
from .live_server import UPLOAD_TIMEOUT_S, live_server, offline, ws_url
from .test_api_docs import validator
from .waiting import wait_until

FRAMES = 40


@pytest.fixture(scope="module")
def full():
    return load_models(get_settings().weights_dir)


@pytest.fixture(scope="module")
def cores():
    return load_models(get_settings().weights_dir, core_only=True)


@pytest.fixture(scope="module")
def server(full, cores, tmp_path_factory):
    styles_dir = tmp_path_factory.mktemp("styles")
    with live_server(full, core_models=cores, idle_timeout_s=30, styles_dir=styles_dir) as (base, app):
        yield base, app.state.runtime


@pytest.fixture(scope="module")
def walk(bn_walk):
    m = bn_walk.slice(0, FRAMES)
    return m.translations[:, 1].copy(), m.rotations.copy()


def start(ws, **fields) -> dict:
    ws.send(json.dumps({"type": "start", **fields}))
    return json.loads(ws.recv(timeout=30))


def stream(ws, root: np.ndarray, rot: np.ndarray, seq0: int = 0) -> tuple[np.ndarray, np.ndarray]:
    roots, rots = [], []
    for t in range(len(root)):
        ws.send(json.dumps({"type": "frame", "seq": seq0 + t, "root": root[t].tolist(), "rotations": rot[t].tolist()}))
        reply = json.loads(ws.recv(timeout=30))
        assert reply["type"] == "frame" and reply["seq"] == seq0 + t, reply
        roots.append(reply["root"])
        rots.append(reply["rotations"])
    return np.array(roots), np.array(rots)


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Largest angle between matching quaternions, in degrees."""
    return float(np.degrees(2 * np.arccos(np.abs((a * b).sum(-1)).clip(0, 1))).max())


@pytest.mark.parametrize("name", ["lti", "erd", "lpn"])
def test_a_core_session_streams_the_core_alone(server, full, cores, walk, name):
    base, _ = server
    style = cores[name].styles()[-1]
    root, rot = walk
    with connect(ws_url(base)) as ws:
        started = start(ws, model=name, pipeline="core", style=style)
        assert (started["type"], started["model"], started["pipeline"]) == ("started", name, "core"), started
        assert started["styles"] == cores[name].styles()
        validator("Started").validate(started)  # as service/asyncapi.yaml documents it
        got_root, got_rot = stream(ws, root, rot)
    want_root, want_rot = offline(cores[name], {style: 1.0}, root, rot)
    np.testing.assert_allclose(got_root, want_root, atol=1e-5)
    np.testing.assert_allclose(got_rot, want_rot, atol=1e-5)
    shipped_root, shipped_rot = offline(full[name], {style: 1.0}, root, rot)
    assert angle_deg(got_rot, shipped_rot) > 1.0, "the core session streamed the shipped pipeline"


def test_models_say_which_pipelines_they_offer(server, full, walk):
    base, _ = server
    listed = {m["name"]: m["pipelines"] for m in httpx.get(f"{base}/v1/models").json()}
    assert listed == {name: ["full", "core"] for name in full}
    with Client(base) as client:
        assert {m.name: m.pipelines for m in client.models()} == listed
    with live_server({"lti": full["lti"]}) as (alone, _):  # no cores given: the full pipeline only
        assert httpx.get(f"{alone}/v1/models").json()[0]["pipelines"] == ["full"]
        with connect(ws_url(alone)) as ws:
            refused = start(ws, model="lti", pipeline="core", style=full["lti"].styles()[0])
        assert refused["code"] == "pipeline_unavailable", refused


def test_an_unknown_pipeline_is_a_schema_error(server, full):
    base, _ = server
    with connect(ws_url(base)) as ws:
        refused = start(ws, model="lti", pipeline="stages", style=full["lti"].styles()[0])
    assert (refused["type"], refused["code"]) == ("error", "bad_message") and "pipeline" in refused["message"]


def test_an_uploaded_style_is_refused_by_the_core_with_a_typed_error(server, index):
    from models.data import load_motion, select

    base, _ = server
    clip = load_motion(select(index, dataset="bandai-namco-1", style="giant", content="walk")[0]).slice(0, 240)
    body = {"name": "pipe-giant", "model": "lpn", "frames": frames_json(clip), "fps": 30}
    reply = httpx.post(f"{base}/v1/styles", json=body, timeout=UPLOAD_TIMEOUT_S)
    assert reply.status_code == 201, reply.text
    with connect(ws_url(base)) as ws:
        refused = start(ws, model="lpn", pipeline="core", style="pipe-giant")
    assert refused["code"] == "style_not_in_pipeline", refused
    with connect(ws_url(base)) as ws:  # the full pipeline takes it; a core session's restyle does not
        assert start(ws, model="lpn", style="pipe-giant")["type"] == "started"
    with connect(ws_url(base)) as ws:
        assert start(ws, model="lpn", pipeline="core", style="normal")["type"] == "started"
        ws.send(json.dumps({"type": "style", "style": "pipe-giant"}))
        assert json.loads(ws.recv(timeout=30))["code"] == "style_not_in_pipeline"
        ws.send(json.dumps({"type": "style", "style": "no-such-style"}))
        assert json.loads(ws.recv(timeout=30))["code"] == "unknown_style"
    with Client(base, timeout=30) as client, client.crowd([Character(1, "lpn", "pipe-giant", pipeline="core")]) as c:
        assert [(e.character, e.code) for e in c.errors] == [(1, "style_not_in_pipeline")]


def test_a_crowd_mixes_pipelines_each_character_as_its_own(server, full, cores, walk):
    base, _ = server
    root, rot = walk
    style = cores["lti"].styles()[-1]  # where the fitted stages change the walk most visibly
    chars = [
        Character(1, "lti", style),
        Character(2, "lti", style, pipeline="core"),
        Character(3, "erd", cores["erd"].styles()[0], pipeline="core"),
    ]
    got: dict[int, list] = {1: [], 2: [], 3: []}
    with Client(base, timeout=30) as client, client.crowd(chars) as crowd:
        assert crowd.errors == [] and sorted(crowd.characters) == [1, 2, 3]
        for t in range(FRAMES):
            out = crowd.tick([1, 2, 3], np.tile(root[t], (3, 1)), np.tile(rot[t], (3, 1, 1)))
            for i in (1, 2, 3):
                got[i].append(out.frame(i)[1].copy())
    wants = {
        1: offline(full["lti"], {style: 1.0}, root, rot)[1],
        2: offline(cores["lti"], {style: 1.0}, root, rot)[1],
        3: offline(cores["erd"], {cores["erd"].styles()[0]: 1.0}, root, rot)[1],
    }
    for i, want in wants.items():
        np.testing.assert_allclose(np.array(got[i]), want, atol=1e-5, err_msg=f"character {i}")
    assert angle_deg(np.array(got[1]), np.array(got[2])) > 1.0  # one method, two pipelines: not one state


@pytest.fixture(scope="module", params=["memory", "redis"])
def store_server(request, full, cores, tmp_path_factory):
    lti = {"lti": full["lti"]}, {"lti": cores["lti"]}
    if request.param == "memory":
        with live_server(lti[0], core_models=lti[1], idle_timeout_s=30) as (base, app):
            yield base, app.state.runtime
        return
    require("redis-server")
    with (
        redis_server(tmp_path_factory.mktemp("redis")) as url,
        live_server(lti[0], core_models=lti[1], idle_timeout_s=30, session_store=url) as (base, app),
    ):
        yield base, app.state.runtime


def test_a_resumed_core_session_stays_on_the_core(store_server, cores, walk):
    base, runtime = store_server
    root, rot = walk
    style, half = cores["lti"].styles()[1], FRAMES // 2
    with connect(ws_url(base)) as ws:  # dropped after the first half
        token = start(ws, model="lti", pipeline="core", style=style)["resume_token"]
        first = stream(ws, root[:half], rot[:half])
    wait_until(lambda: not runtime.sessions, "the dropped session to be stored")
    with connect(ws_url(base)) as ws:  # the stored pipeline wins over the start's (default) one
        resumed = start(ws, model="lti", resume_token=token)
        assert (resumed["type"], resumed.get("pipeline"), resumed.get("last_seq")) == ("started", "core", half - 1), (
            resumed
        )
        second = stream(ws, root[half:], rot[half:], seq0=half)
    want_root, want_rot = offline(cores["lti"], {style: 1.0}, root, rot)
    np.testing.assert_allclose(np.concatenate([first[0], second[0]]), want_root, atol=1e-5)
    np.testing.assert_allclose(np.concatenate([first[1], second[1]]), want_rot, atol=1e-5)


def test_a_snapshot_saved_before_pipelines_resumes_the_full_pipeline():
    fields = {
        "session_id": "s",
        "token": "t",
        "model": "lti",
        "skeleton": "bandai-namco",
        "bvh_header": None,
        "fps": 30.0,
        "encoding": "json",
        "weights": {},
        "target": {},
        "transition_left": 0,
        "last_seq": None,
        "clock": -1.0,
        "held": {},
        "state": {},
        "saved_at": 0.0,
    }
    assert Snapshot.from_json(json.dumps(fields)).pipeline == "full"
    core = Snapshot(**fields, pipeline="core")
    assert Snapshot.from_bytes(core.to_bytes()).pipeline == "core"


def test_the_sdk_opens_a_core_session(server, cores, walk):
    base, _ = server
    root, rot = walk
    style = cores["erd"].styles()[0]
    with Client(base, timeout=30) as client, client.session(model="erd", style=style, pipeline="core") as s:
        assert s.info["pipeline"] == "core"
        got = np.array([s.stylise(root[t], rot[t]).rotations for t in range(len(root))])
    np.testing.assert_allclose(got, offline(cores["erd"], {style: 1.0}, root, rot)[1], atol=1e-5)
