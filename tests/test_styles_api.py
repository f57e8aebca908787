"""REST styles and jobs against a real server on loopback: listing, upload validation, LTI
fine-tuning from an uploaded clip, using the new style in a live session, deletion."""

from __future__ import annotations

import json
import time

import httpx
import numpy as np
import pytest
from websockets.sync.client import connect

from models.data import select
from models.interface import FrameBatch, style_vector
from models.lti.finetune import ExtensibleLTIModel
from models.registry import load_models
from models.settings import get_settings

from .live_server import live_server

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
    m = load_motion(select(index, dataset="bandai-namco-2", style="elderly", content="walk", split="test")[0]).slice(0, 300)
    return m.translations[:, 1].copy(), m.rotations.copy()


def payload(name, root, rot, **extra) -> dict:
    return {"name": name, "model": "lti", "frames": {"root": np.asarray(root).tolist(), "rotations": np.asarray(rot).tolist()},
            "fps": 30, **extra}


def ws_url(base: str) -> str:
    return base.replace("http", "ws") + "/v1/stream"


def stream(ws, root, rot, seq0=0):
    out = []
    for t in range(len(root)):
        ws.send(json.dumps({"type": "frame", "seq": seq0 + t, "root": root[t].tolist(), "rotations": rot[t].tolist()}))
        reply = json.loads(ws.recv(timeout=20))
        assert reply["type"] == "frame" and reply["seq"] == seq0 + t, reply
        out.append(reply["rotations"])
    return np.array(out)


def offline(model, style, root, rot):
    state, w, out = model.init_state(1), style_vector(model, {style: 1.0})[None], []
    for t in range(len(root)):
        fb, state = model.step_batch(state, FrameBatch(root[t:t + 1], rot[t:t + 1]), w)
        out.append(fb.rotations[0])
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
    return ("HIERARCHY\nROOT Pelvis\n{\n OFFSET 0 0 0\n CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation\n"
            " JOINT Knee\n {\n  OFFSET 0 -40 0\n  CHANNELS 3 Zrotation Xrotation Yrotation\n  End Site\n  {\n   OFFSET 0 -40 0\n  }\n }\n}\n"
            "MOTION\nFrames: 90\nFrame Time: 0.0333333\n" + "0 90 0 0 0 0 0 0 0\n" * 90)


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
    cases.append((httpx.post(url, content=json.dumps(payload("nanny", bad, rot[:90])), headers={"content-type": "application/json"}), 422, "non_finite"))
    cases.append((httpx.post(url, json=payload("short", root[:10], rot[:10])), 422, "bad_length"))
    cases.append((httpx.post(url, json=payload("Bad Name!", root[:90], rot[:90])), 422, "bad_name"))
    cases.append((httpx.post(url, json=payload("elderly", root[:90], rot[:90])), 409, "style_exists"))
    cases.append((httpx.post(url, json=payload("wrongjoints", root[:90], rot[:90, :10])), 422, "bad_skeleton"))
    cases.append((httpx.post(f"{base}/v1/styles", json=payload("nofinetune", root[:90], rot[:90])), 422, "fine_tune_required"))
    for r, status, code in cases:
        assert r.status_code == status, (status, code, r.text[:300])
        body = r.json()
        assert body["code"] == code and body["message"], body


def test_cmu_bvh_is_retargeted_and_accepted(server, index):
    """A CMU-skeleton BVH passes validation (retargeted); without fine_tune the LTI model says why not."""
    clip = select(index, dataset="xia", style="neutral", content="walk")[0]
    r = httpx.post(f"{server[0]}/v1/styles", files={"file": ("walk.bvh", clip.path.read_bytes())},
                   data={"name": "cmu-walk", "model": "lti"})
    assert r.status_code == 422 and r.json()["code"] == "fine_tune_required", r.text


def test_adding_a_style_pads_older_states(models, styled_clip):
    """A state from before a style was added continues exactly on the extended model."""
    from models.lti.model import StyleTranslator
    root, rot = styled_clip
    base = ExtensibleLTIModel.from_model(models["lti"])
    tr = models["lti"].translators["elderly"]
    extra = StyleTranslator("zz-copy", tr.A, tr.B, tr.C, tr.D, tr.in_mean, tr.in_std, tr.out_mean, tr.out_std,
                            tr.in_lo, tr.in_hi, tr.orders, tr.k_p, tr.k_c, tr.footplant, {}, tr.ref)
    bigger = base.with_translator(extra)
    assert bigger.styles() == base.styles() + ["zz-copy"] and base.styles() == models["lti"].styles()
    w_old = style_vector(base, {"exhausted": 1.0})[None]
    state = base.init_state(1)
    for t in range(20):
        _, state = base.step_batch(state, FrameBatch(root[t:t + 1], rot[t:t + 1]), w_old)
    s_old, s_new = dict(state), dict(state)
    for t in range(20, 40):
        a, s_old = base.step_batch(s_old, FrameBatch(root[t:t + 1], rot[t:t + 1]), w_old)
        b, s_new = bigger.step_batch(s_new, FrameBatch(root[t:t + 1], rot[t:t + 1]), w_old)  # short state and weights
        np.testing.assert_allclose(a.rotations, b.rotations, atol=1e-12)
    assert s_new["x"].shape[1] == bigger.state_dim > base.state_dim


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
        r = httpx.post(f"{base}/v1/styles?fine_tune=true", json=payload("my-elderly", root, rot), timeout=30)
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
        want = offline(models["lti"], "exhausted", w_root, w_rot)
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


def test_uploaded_styles_reload_at_startup(models, styled_clip, tmp_path):
    root, rot = styled_clip
    with live_server(models, styles_dir=tmp_path) as (base, _):
        job = httpx.post(f"{base}/v1/styles?fine_tune=true", json=payload("kept", root[:200], rot[:200]), timeout=30).json()["job"]
        for _ in range(600):
            if httpx.get(f"{base}/v1/jobs/{job['id']}").json()["status"] in ("done", "failed"):
                break
            time.sleep(0.2)
    with live_server(models, styles_dir=tmp_path) as (base, _):
        info = httpx.get(f"{base}/v1/styles/lti.kept").json()
        assert info["status"] == "ready" and info["kind"] == "uploaded"
        with connect(ws_url(base)) as ws:
            ws.send(json.dumps({"type": "start", "model": "lti", "style": "kept"}))
            assert json.loads(ws.recv(timeout=10))["type"] == "started"
