"""Two replicas sharing one styles folder (`styles_refresh_s` > 0), as in docker/compose.yaml: an
LPN-FiLM style uploaded through one is usable on the other at once with the same output, its
fine-tuned FiLM vector and a finished LTI job reach the other, and a delete through either removes
it from both. The periodic rescan is set long here: each of these comes from a replica looking at
the folder when a session or a request names what it lacks; a job's progress can be followed on
either. Each replica has its own LPN-FiLM instance, as separate processes do."""

from __future__ import annotations

import httpx
import numpy as np
import pytest

from clients.sdk import Client
from models.data import load_motion, select
from models.lpn import load as load_lpn
from models.lti import load as load_lti
from models.settings import get_settings

from .clips import drive_lpn, frames_json
from .live_server import live_server
from .waiting import wait_until

WALK = [((1.3, 0.0), 0.0, "walk")] * 30
STEPS = 20  # fine-tune steps (the service default is 300)
POLL_S = 0.1  # between polls of a job or a style: under the REST limit, 20 requests a second a client


@pytest.fixture(scope="module")
def chimpira_clip(index):
    return frames_json(
        load_motion(select(index, dataset="bandai-namco-1", style="chimpira", content="walk")[0]).slice(0, 200)
    )


def drive(base: str, style: str) -> np.ndarray:
    return drive_lpn(base, style, WALK)


def styles_of(base: str, model: str = "lpn") -> list[str]:
    return next(m for m in httpx.get(f"{base}/v1/models").json() if m["name"] == model)["styles"]


def lti_outputs(base: str, style: str, root, rot) -> np.ndarray:
    with Client(base).session(model="lti", style=style) as session:
        return np.array([session.stylise(root[t], rot[t]).rotations for t in range(len(root))])


def test_replicas_sharing_a_styles_folder_see_each_others_uploads(chimpira_clip, index, bn_walk, tmp_path):
    weights = get_settings().weights_dir
    lti = load_lti(weights / "lti")  # each server takes its own copy of a model that adds styles
    shared = dict(styles_dir=tmp_path, styles_refresh_s=30, lpn_fine_tune_steps=STEPS)  # rescans come from misses
    with (
        live_server({"lpn": load_lpn(weights / "lpn"), "lti": lti}, **shared) as (a, _),
        # one style message a second on b: the switch below, which makes b look for the style and
        # try again, must count once (it counted twice, and was refused as over the rate)
        live_server({"lpn": load_lpn(weights / "lpn"), "lti": lti}, **shared, max_controls_per_s=1) as (b, _),
    ):
        body = {"name": "street", "model": "lpn", "frames": chimpira_clip, "fps": 30}
        with Client(b).session(model="lpn", style="normal") as waiting:  # open on b before the upload
            waiting.control((1.0, 0.0), 0.0)
            assert httpx.post(f"{a}/v1/styles", json=body, timeout=60).status_code == 201
            # b has not rescanned yet, but a switch to the new style makes it look at once
            assert waiting.set_style("street")["type"] == "style_set"
        # no waiting for the periodic rescan: a session naming an unknown style makes b look at once
        on_a, on_b = drive(a, "street"), drive(b, "street")
        np.testing.assert_allclose(on_b, on_a, atol=1e-5)  # the same FiLM embedding on both
        assert httpx.get(f"{b}/v1/styles/lpn.street").json()["status"] == "ready"

        # fine-tuned on a (its job), the tuned vector reaches b by the rescan
        body = {"name": "tuned", "model": "lpn", "frames": chimpira_clip, "fps": 30, "fine_tune": True}
        reply = httpx.post(f"{a}/v1/styles", json=body, timeout=60)
        assert reply.status_code == 201, reply.text
        job = reply.json()["job"]["id"]
        wait_until(
            lambda: httpx.get(f"{a}/v1/jobs/{job}").json()["status"] in ("done", "failed"),
            "job did not end",
            120,
            POLL_S,
        )
        assert httpx.get(f"{a}/v1/jobs/{job}").json()["status"] == "done"
        tuned_a = httpx.get(f"{a}/v1/styles/lpn.tuned").json()
        assert tuned_a["fine_tune"]["installed"], tuned_a
        wait_until(
            lambda: httpx.get(f"{b}/v1/styles/lpn.tuned").json().get("fine_tune"),
            "b kept the untuned style",
            10,
            POLL_S,
        )
        np.testing.assert_allclose(drive(b, "tuned"), drive(a, "tuned"), atol=1e-5)

        # an LTI style identified by a job on b is taken in by a once the job is done
        m = load_motion(
            select(index, dataset="bandai-namco-2", style="elderly", content="walk", split="test")[0]
        ).slice(0, 300)
        body = {"name": "slow", "model": "lti", "fps": 30, "frames": frames_json(m)}
        reply = httpx.post(f"{b}/v1/styles?fine_tune=true", json=body, timeout=60)
        assert reply.status_code == 202, reply.text
        job = reply.json()["job"]["id"]
        # a, which does not run the job, answers for it from the record b keeps with the style
        seen_on_a = []
        wait_until(
            lambda: (
                seen_on_a.append(httpx.get(f"{a}/v1/jobs/{job}").json())
                or seen_on_a[-1]["status"] in ("done", "failed")
            ),
            "LTI job did not end",
            120,
            POLL_S,
        )
        assert seen_on_a[-1] == httpx.get(f"{b}/v1/jobs/{job}").json()  # the finished record, as b has it
        assert seen_on_a[-1]["status"] == "done" and seen_on_a[-1]["result"]["state_dim"] > 0
        assert {r["id"] for r in seen_on_a} == {job} and {r["status"] for r in seen_on_a} >= {"running", "done"}
        assert httpx.get(f"{a}/v1/jobs/0123abc").status_code == 404
        wait_until(lambda: "slow" in styles_of(a, "lti"), "a did not take in the LTI style")
        walk = bn_walk.slice(0, 40)
        np.testing.assert_allclose(
            lti_outputs(a, "slow", walk.translations[:, 1], walk.rotations),
            lti_outputs(b, "slow", walk.translations[:, 1], walk.rotations),
            atol=1e-6,
        )

        # deleted through b: gone from both, and a new session on it is refused on a
        assert httpx.delete(f"{b}/v1/styles/lpn.street").status_code == 204
        wait_until(lambda: "street" not in styles_of(a), "a still lists the deleted style")
        assert "street" not in styles_of(b) and "tuned" in styles_of(a) and "tuned" in styles_of(b)
        assert httpx.get(f"{a}/v1/styles/lpn.street").status_code == 404
