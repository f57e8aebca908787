"""A new LPN-FiLM style from an uploaded clip over REST: usable at once (the FiLM generator's
embedding of the clip, no job), used by a live controller session, back after a restart,
deletable; fine-tuning is refused with a typed error."""

from __future__ import annotations

import httpx
import numpy as np
import pytest

from clients.sdk import Client
from models.data import load_motion, select
from models.registry import load_models
from models.settings import get_settings

from .live_server import live_server

MODEL = load_models(get_settings().weights_dir)["lpn"]
WALK = [((1.3, 0.0), 0.0, "walk")] * 45


@pytest.fixture(scope="module")
def giant_clip(index):
    """A walk of a style LPN-FiLM never saw in training (held out for this experiment)."""
    m = load_motion(select(index, dataset="bandai-namco-1", style="giant", content="walk")[0]).slice(0, 240)
    return {"root": m.translations[:, 1].tolist(), "rotations": m.rotations.tolist()}


def drive(base: str, style: str) -> np.ndarray:
    with Client(base).session(model="lpn", style=style) as session:
        return np.array([session.control(v, facing, gait).rotations for v, facing, gait in WALK])


def test_an_uploaded_clip_is_a_live_lpn_style_at_once_and_after_a_restart(giant_clip, tmp_path):
    body = {"name": "my-giant", "model": "lpn", "frames": giant_clip, "fps": 30}
    with live_server({"lpn": MODEL}, styles_dir=tmp_path) as (base, _):
        refused = httpx.post(f"{base}/v1/styles", json={**body, "fine_tune": True})
        assert refused.status_code == 422 and refused.json()["code"] == "fine_tune_unsupported"

        reply = httpx.post(f"{base}/v1/styles", json=body, timeout=60)
        assert reply.status_code == 201, reply.text  # created, not accepted for a job
        style = reply.json()["style"]
        assert (style["id"], style["status"], reply.json()["job"]) == ("lpn.my-giant", "ready", None)
        assert "my-giant" in httpx.get(f"{base}/v1/models").json()[0]["styles"]

        giant, normal = drive(base, "my-giant"), drive(base, "normal")
        assert np.isfinite(giant).all()
        # the new style changes the body's motion: mean joint-rotation difference above a degree
        dots = np.abs((giant * normal).sum(-1)).clip(0, 1)
        assert np.degrees(2 * np.arccos(dots)).mean() > 1.0

    MODEL.remove_style("my-giant")  # what a fresh process would have: only the trained styles
    with live_server({"lpn": MODEL}, styles_dir=tmp_path) as (base, _):  # a restarted server
        assert httpx.get(f"{base}/v1/styles/lpn.my-giant").json()["status"] == "ready"
        np.testing.assert_allclose(drive(base, "my-giant"), giant, atol=1e-5)
        assert httpx.delete(f"{base}/v1/styles/lpn.my-giant").status_code == 204
        assert "my-giant" not in httpx.get(f"{base}/v1/models").json()[0]["styles"]
