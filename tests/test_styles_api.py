"""REST styles and jobs against a real server on loopback: listing, upload validation, LTI
fine-tuning from an uploaded clip, using the new style in a live session, deletion."""

from __future__ import annotations

import copy
import json
import threading
import time

import httpx
import numpy as np
import pytest
from websockets.sync.client import connect

from models.data import select
from models.interface import FrameBatch, style_vector
from models.registry import load_models
from models.settings import get_settings

from .live_server import UPLOAD_TIMEOUT_S, live_server, offline, ws_url

LIMIT = 2 * 1024 * 1024


@pytest.fixture(scope="module")
def models():
    return load_models(get_settings().weights_dir)


@pytest.fixture(scope="module")
def server(models, tmp_path_factory):
    styles_dir = tmp_path_factory.mktemp("styles")
    with live_server(models, styles_dir=styles_dir, upload_max_bytes=LIMIT, idle_timeout_s=60) as (base, app):
        yield base, app, styles_dir


@pytest.fixture(scope="module")
def styled_clip(index):
    from models.data import load_motion

    m = load_motion(select(index, dataset="bandai-namco-2", style="elderly", content="walk", split="test")[0]).slice(
        0, 300
    )
    return m.translations[:, 1].copy(), m.rotations.copy()


def payload(name, root, rot, **extra) -> dict:
    return {
        "name": name,
        "model": "lti",
        "frames": {"root": np.asarray(root).tolist(), "rotations": np.asarray(rot).tolist()},
        "fps": 30,
        **extra,
    }


def stream(ws, root, rot, seq0=0):
    out = []
    for t in range(len(root)):
        ws.send(json.dumps({"type": "frame", "seq": seq0 + t, "root": root[t].tolist(), "rotations": rot[t].tolist()}))
        reply = json.loads(ws.recv(timeout=20))
        assert reply["type"] == "frame" and reply["seq"] == seq0 + t, reply
        out.append(reply["rotations"])
    return np.array(out)


def test_list_and_get_trained_styles(server, models):
    base = server[0]
    styles = httpx.get(f"{base}/v1/styles").json()
    trained = {s["name"] for s in styles if s["model"] == "lti" and s["kind"] == "trained"}
    assert trained == set(models["lti"].styles())
    one = httpx.get(f"{base}/v1/styles/lti.elderly").json()
    assert one["id"] == "lti.elderly" and one["status"] == "ready" and one["kind"] == "trained" and one["created"]
    assert httpx.get(f"{base}/v1/styles?model=lti").status_code == 200
    missing = httpx.get(f"{base}/v1/styles/lti.nope")
    assert missing.status_code == 404 and missing.json()["code"] == "unknown_style"


def test_trained_style_cannot_be_deleted(server):
    r = httpx.delete(f"{server[0]}/v1/styles/lti.elderly")
    assert r.status_code == 409 and r.json()["code"] == "trained_style" and "trained" in r.json()["message"]
    assert httpx.delete(f"{server[0]}/v1/styles/lti.nope").status_code == 404


def _bad_bvh() -> str:
    return (
        "HIERARCHY\nROOT Pelvis\n{\n OFFSET 0 0 0\n CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation\n"
        " JOINT Knee\n {\n  OFFSET 0 -40 0\n  CHANNELS 3 Zrotation Xrotation Yrotation\n  End Site\n  {\n   OFFSET 0 -40 0\n  }\n }\n}\n"
        "MOTION\nFrames: 90\nFrame Time: 0.0333333\n" + "0 90 0 0 0 0 0 0 0\n" * 90
    )


def test_upload_validation_errors(server, styled_clip):
    base = server[0]
    root, rot = styled_clip
    url = f"{base}/v1/styles?fine_tune=true"
    cases = []
    r = httpx.post(url, content=b"{" + b" " * (LIMIT + 10) + b"}", headers={"content-type": "application/json"})
    cases.append((r, 413, "too_large"))
    r = httpx.post(url, files={"file": ("x.bvh", _bad_bvh())}, data={"name": "pelvis", "model": "lti"})
    cases.append((r, 422, "unsupported_skeleton"))
    bad = root[:90].copy()
    bad[5, 1] = np.nan
    cases.append(
        (
            httpx.post(
                url, content=json.dumps(payload("nanny", bad, rot[:90])), headers={"content-type": "application/json"}
            ),
            422,
            "non_finite",
        )
    )

    def post(url: str, body: dict) -> httpx.Response:
        return httpx.post(url, json=body, timeout=UPLOAD_TIMEOUT_S)

    cases.append((post(url, payload("short", root[:10], rot[:10])), 422, "bad_length"))
    cases.append((post(url, payload("Bad Name!", root[:90], rot[:90])), 422, "bad_name"))
    cases.append((post(url, payload("elderly", root[:90], rot[:90])), 409, "style_exists"))
    cases.append((post(url, payload("wrongjoints", root[:90], rot[:90, :10])), 422, "bad_skeleton"))
    cases.append((post(f"{base}/v1/styles", payload("nofinetune", root[:90], rot[:90])), 422, "fine_tune_required"))
    for r, status, code in cases:
        assert r.status_code == status, (status, code, r.text[:300])
        body = r.json()
        assert body["code"] == code and body["message"], body


def test_cmu_bvh_is_retargeted_and_accepted(server, index):
    """A CMU-skeleton BVH passes validation (retargeted); without fine_tune the LTI model says why not."""
    clip = select(index, dataset="xia", style="neutral", content="walk")[0]
    r = httpx.post(
        f"{server[0]}/v1/styles",
        files={"file": ("walk.bvh", clip.path.read_bytes())},
        data={"name": "cmu-walk", "model": "lti"},
        timeout=UPLOAD_TIMEOUT_S,
    )
    assert r.status_code == 422 and r.json()["code"] == "fine_tune_required", r.text


def _copy_translator(tr, name: str):
    from models.lti.model import StyleTranslator

    return StyleTranslator(
        name,
        tr.A,
        tr.B,
        tr.C,
        tr.D,
        tr.in_mean,
        tr.in_std,
        tr.out_mean,
        tr.out_std,
        tr.in_lo,
        tr.in_hi,
        tr.orders,
        tr.k_p,
        tr.k_c,
        tr.footplant,
        {},
        tr.ref,
    )


def test_adding_a_style_upgrades_older_states(models, styled_clip):
    """A state from before a style was added continues exactly on the extended model."""
    root, rot = styled_clip
    base = models["lti"]
    before = base.styles()
    bigger = copy.copy(base)  # a copy's style set changes independently
    bigger.add_style(_copy_translator(base.translators["elderly"], "zz-copy"))
    assert bigger.styles() == before + ["zz-copy"] and base.styles() == before
    state = base.init_state(1)
    for t in range(20):
        _, state = base.step_batch(
            state, FrameBatch(root[t : t + 1], rot[t : t + 1]), style_vector(base, {"exhausted": 1.0})[None]
        )
    s_old, s_new = dict(state), dict(state)
    for t in range(20, 40):
        a, s_old = base.step_batch(
            s_old, FrameBatch(root[t : t + 1], rot[t : t + 1]), style_vector(base, {"exhausted": 1.0})[None]
        )
        b, s_new = bigger.step_batch(
            bigger.upgrade_state(s_new),
            FrameBatch(root[t : t + 1], rot[t : t + 1]),
            style_vector(bigger, {"exhausted": 1.0})[None],
        )  # state from before the add
        np.testing.assert_allclose(a.rotations, b.rotations, atol=1e-12)
    assert "x.zz-copy" not in state and s_new["x.zz-copy"].shape[1] == bigger.translators["zz-copy"].n
    assert _state_dim(bigger) > _state_dim(base)
    assert bigger.upgrade_state(s_new) is s_new  # nothing changed: the same state back


def _state_dim(model) -> int:
    """Total LTI state size over all styles."""
    return sum(model.translators[s].n for s in model.styles())


def test_removing_a_style_keeps_other_states_and_drops_its_own(models, styled_clip):
    root, rot = styled_clip
    model = copy.copy(models["lti"])
    model.add_style(_copy_translator(model.translators["elderly"], "zz-gone"))
    state = model.init_state(1)
    for t in range(10):
        _, state = model.step_batch(
            state,
            FrameBatch(root[t : t + 1], rot[t : t + 1]),
            style_vector(model, {"exhausted": 0.5, "zz-gone": 0.5})[None],
        )
    model.remove_style("zz-gone")
    assert "zz-gone" not in model.styles() and "zz-gone" not in models["lti"].styles()
    up = model.upgrade_state(state)
    assert "x.zz-gone" not in up and up["x.exhausted"] is state["x.exhausted"]
    with pytest.raises(KeyError):
        model.remove_style("zz-gone")


def test_fine_tune_upload_job_session_delete(server, models, styled_clip, bn_walk):
    base, app, styles_dir = server
    root, rot = styled_clip
    walk = bn_walk.slice(0, 60)
    w_root, w_rot = walk.translations[:, 1].copy(), walk.rotations.copy()
    with connect(ws_url(base)) as live:  # a session opened before the style exists keeps streaming
        live.send(json.dumps({"type": "start", "model": "lti", "style": "exhausted"}))
        assert json.loads(live.recv(timeout=10))["type"] == "started"
        first = stream(live, w_root[:30], w_rot[:30])

        t0 = time.monotonic()
        r = httpx.post(
            f"{base}/v1/styles?fine_tune=true", json=payload("my-elderly", root, rot), timeout=UPLOAD_TIMEOUT_S
        )
        assert r.status_code == 202, r.text
        accepted = r.json()
        assert accepted["style"]["id"] == "lti.my-elderly" and accepted["style"]["status"] == "training"
        job_id = accepted["job"]["id"]
        seen = []
        while True:
            job = httpx.get(f"{base}/v1/jobs/{job_id}").json()
            seen.append(job["progress"])
            if job["status"] in ("done", "failed"):
                break
            assert time.monotonic() - t0 < 120
            time.sleep(0.2)
        elapsed = time.monotonic() - t0
        assert job["status"] == "done", job
        assert job["progress"] == 1.0 and seen == sorted(seen) and job["finished"] >= job["created"]
        print(f"fine-tune job: {elapsed:.1f} s, {job['result']}")
        info = httpx.get(f"{base}/v1/styles/lti.my-elderly").json()
        assert info["kind"] == "uploaded" and info["status"] == "ready" and info["fine_tune"]["neutral_clips"]
        assert "lti.my-elderly" in {s["id"] for s in httpx.get(f"{base}/v1/styles").json()}
        assert "my-elderly" in next(m for m in httpx.get(f"{base}/v1/models").json() if m["name"] == "lti")["styles"]
        assert (styles_dir / "lti" / "my-elderly" / "translator.npz").exists()

        # the old session carries on exactly as the original model would have it
        second = stream(live, w_root[30:], w_rot[30:], seq0=30)
        want = offline(models["lti"], {"exhausted": 1.0}, w_root, w_rot)[1]
        np.testing.assert_allclose(np.concatenate([first, second]), want, atol=1e-9)

        # a new session uses the new style, and it changes the motion
        with connect(ws_url(base)) as ws:
            ws.send(json.dumps({"type": "start", "model": "lti", "style": "my-elderly"}))
            started = json.loads(ws.recv(timeout=10))
            assert started["type"] == "started" and "my-elderly" in started["styles"]
            out = stream(ws, w_root, w_rot)
        assert np.all(np.isfinite(out))
        q_in = w_rot / np.linalg.norm(w_rot, axis=-1, keepdims=True)
        assert np.abs(np.abs((out * q_in).sum(-1)) - 1).max() > 1e-3  # rotations differ from the input

    dup = httpx.post(f"{base}/v1/styles?fine_tune=true", json=payload("my-elderly", root[:90], rot[:90]))
    assert dup.status_code == 409 and dup.json()["code"] == "style_exists"
    assert httpx.delete(f"{base}/v1/styles/lti.my-elderly").status_code == 204
    assert httpx.get(f"{base}/v1/styles/lti.my-elderly").status_code == 404
    assert not (styles_dir / "lti" / "my-elderly").exists()
    with connect(ws_url(base)) as ws:
        ws.send(json.dumps({"type": "start", "model": "lti", "style": "my-elderly"}))
        assert json.loads(ws.recv(timeout=10))["code"] == "unknown_style"


def _wait_job(base: str, job_id: str) -> dict:
    t0 = time.monotonic()
    while True:
        job = httpx.get(f"{base}/v1/jobs/{job_id}").json()
        if job["status"] in ("done", "failed"):
            return job
        assert time.monotonic() - t0 < 120
        time.sleep(0.2)


def test_sessions_stream_on_unchanged_across_an_upload_and_a_delete(server, models, styled_clip, bn_walk):
    """Styles added (fine-tuned) and deleted mid-stream: a session on a trained style, one streaming
    all along and one resumed from a snapshot taken in between, give exactly the output of the
    original model; one whose mix had weight on the deleted style is told so and streams on."""
    base = server[0]
    root, rot = styled_clip
    walk = bn_walk.slice(0, 60)
    w_root, w_rot = walk.translations[:, 1].copy(), walk.rotations.copy()
    background: list = []
    stop = threading.Event()

    def stream_all_along() -> None:  # steps keep running while the style set changes
        with connect(ws_url(base)) as ws:
            ws.send(json.dumps({"type": "start", "model": "lti", "style": "elderly"}))
            assert json.loads(ws.recv(timeout=10))["type"] == "started"
            t = 0
            while not stop.is_set() or t < 60:
                k = t % len(w_root)
                background.append(stream(ws, w_root[k : k + 1], w_rot[k : k + 1], seq0=t)[0])
                t += 1
                time.sleep(0.003)

    thread = threading.Thread(target=stream_all_along)
    thread.start()
    try:
        with connect(ws_url(base)) as ws:
            ws.send(json.dumps({"type": "start", "model": "lti", "style": "exhausted"}))
            token = json.loads(ws.recv(timeout=10))["resume_token"]
            first = stream(ws, w_root[:20], w_rot[:20])
            r = httpx.post(
                f"{base}/v1/styles?fine_tune=true",
                json=payload("mid-a", root[:200], rot[:200]),
                timeout=UPLOAD_TIMEOUT_S,
            )
            assert r.status_code == 202, r.text
            assert _wait_job(base, r.json()["job"]["id"])["status"] == "done"
            second = stream(ws, w_root[20:35], w_rot[20:35], seq0=20)  # the session's state now upgraded
        with connect(ws_url(base)) as mixed:  # a session that uses the new style, when it gets deleted
            mixed.send(json.dumps({"type": "start", "model": "lti", "mix": {"exhausted": 0.5, "mid-a": 0.5}}))
            assert json.loads(mixed.recv(timeout=10))["type"] == "started"
            stream(mixed, w_root[:5], w_rot[:5])
            assert httpx.delete(f"{base}/v1/styles/lti.mid-a").status_code == 204
            mixed.send(
                json.dumps({"type": "frame", "seq": 5, "root": w_root[5].tolist(), "rotations": w_rot[5].tolist()})
            )
            error = json.loads(mixed.recv(timeout=10))
            assert error["type"] == "error" and error["code"] == "style_deleted" and error["seq"] == 5, error
            assert "mid-a" in error["message"]
            assert json.loads(mixed.recv(timeout=10))["seq"] == 5
            stream(mixed, w_root[6:10], w_rot[6:10], seq0=6)  # no more notices, frames flow
        with connect(ws_url(base)) as ws:  # resumed from a snapshot made while mid-a existed
            ws.send(json.dumps({"type": "start", "model": "lti", "style": "exhausted", "resume_token": token}))
            assert json.loads(ws.recv(timeout=10))["last_seq"] == 34
            third = stream(ws, w_root[35:], w_rot[35:], seq0=35)
    finally:
        stop.set()
        thread.join()
    want = offline(models["lti"], {"exhausted": 1.0}, w_root, w_rot)[1]
    np.testing.assert_allclose(np.concatenate([first, second, third]), want, atol=1e-9)
    n = len(background)
    idx = np.arange(n) % len(w_root)
    np.testing.assert_allclose(
        np.array(background), offline(models["lti"], {"elderly": 1.0}, w_root[idx], w_rot[idx])[1], atol=1e-9
    )
    assert "mid-a" not in next(m for m in httpx.get(f"{base}/v1/models").json() if m["name"] == "lti")["styles"]


def test_uploaded_styles_and_their_job_records_reload_at_startup(models, styled_clip, tmp_path):
    root, rot = styled_clip
    with live_server(models, styles_dir=tmp_path) as (base, _):
        job = httpx.post(
            f"{base}/v1/styles?fine_tune=true", json=payload("kept", root[:200], rot[:200]), timeout=30
        ).json()["job"]
        for _ in range(600):
            if httpx.get(f"{base}/v1/jobs/{job['id']}").json()["status"] in ("done", "failed"):
                break
            time.sleep(0.2)
        finished = httpx.get(f"{base}/v1/jobs/{job['id']}").json()
    with live_server(models, styles_dir=tmp_path) as (base, _):
        info = httpx.get(f"{base}/v1/styles/lti.kept").json()
        assert info["status"] == "ready" and info["kind"] == "uploaded"
        assert httpx.get(f"{base}/v1/jobs/{job['id']}").json() == finished  # its record survives the restart
        with connect(ws_url(base)) as ws:
            ws.send(json.dumps({"type": "start", "model": "lti", "style": "kept"}))
            assert json.loads(ws.recv(timeout=10))["type"] == "started"
