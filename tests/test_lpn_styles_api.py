"""A new LPN-FiLM style from an uploaded clip over REST: usable at once (the FiLM generator's
embedding of the clip, no job), used by a live controller session, back after a restart,
deletable; with fine_tune=true also a background job that fine-tunes the FiLM generator on the
clip and swaps in the tuned FiLM vector while sessions on the style stream on. Each server
changes its own copy of the model's style set (`app.state.runtime.models`), never MODEL's."""

from __future__ import annotations

import threading
import time

import httpx
import numpy as np
import pytest

from clients.sdk import Client
from models.data import load_motion, select
from models.registry import load_models
from models.settings import get_settings

from .clips import drive_lpn, frames_json
from .live_server import UPLOAD_TIMEOUT_S, live_server
from .lpn_films import film_of
from .waiting import wait_until

MODEL = load_models(get_settings().weights_dir)["lpn"]
WALK = [((1.3, 0.0), 0.0, "walk")] * 45
STEPS = 40  # fine-tune steps in these tests (the service default is 300)


@pytest.fixture(scope="module")
def giant_clip(index):
    """A walk of a style LPN-FiLM never saw in training (held out for this experiment)."""
    return frames_json(
        load_motion(select(index, dataset="bandai-namco-1", style="giant", content="walk")[0]).slice(0, 240)
    )


def drive(base: str, style: str) -> np.ndarray:
    return drive_lpn(base, style, WALK)


def test_an_uploaded_clip_is_a_live_lpn_style_at_once_and_after_a_restart(giant_clip, tmp_path):
    body = {"name": "my-giant", "model": "lpn", "frames": giant_clip, "fps": 30}
    with live_server({"lpn": MODEL}, styles_dir=tmp_path) as (base, _):
        reply = httpx.post(f"{base}/v1/styles", json=body, timeout=UPLOAD_TIMEOUT_S)
        assert reply.status_code == 201, reply.text  # created, not accepted for a job
        style = reply.json()["style"]
        assert (style["id"], style["status"], reply.json()["job"]) == ("lpn.my-giant", "ready", None)
        assert "my-giant" in httpx.get(f"{base}/v1/models").json()[0]["styles"]

        giant, normal = drive(base, "my-giant"), drive(base, "normal")
        assert np.isfinite(giant).all()
        # the new style changes the body's motion: mean joint-rotation difference above a degree
        dots = np.abs((giant * normal).sum(-1)).clip(0, 1)
        assert np.degrees(2 * np.arccos(dots)).mean() > 1.0

    assert (
        "my-giant" not in MODEL.styles()
    )  # the server's style set was its own: a restart starts from the trained ones
    with live_server({"lpn": MODEL}, styles_dir=tmp_path) as (base, _):  # a restarted server
        assert httpx.get(f"{base}/v1/styles/lpn.my-giant").json()["status"] == "ready"
        np.testing.assert_allclose(drive(base, "my-giant"), giant, atol=1e-5)
        assert httpx.delete(f"{base}/v1/styles/lpn.my-giant").status_code == 204
        assert "my-giant" not in httpx.get(f"{base}/v1/models").json()[0]["styles"]


class Streamer(threading.Thread):
    """A controller session on `style` walking until stopped, every reply kept (with when it came)."""

    def __init__(self, base: str, style: str) -> None:
        super().__init__(daemon=True)
        self.base, self.style = base, style
        self.replies: list[tuple[float, np.ndarray]] = []
        self.error: BaseException | None = None
        self.stop = threading.Event()

    def run(self) -> None:
        try:
            with Client(self.base).session(model="lpn", style=self.style) as session:
                while not self.stop.is_set():
                    self.replies.append((time.monotonic(), session.control((1.3, 0.0), 0.0, "walk").rotations))
                    time.sleep(0.01)
        except BaseException as exc:  # noqa: BLE001 - reported by the test
            self.error = exc


def poll_job(base: str, job_id: str, timeout: float = 120) -> list[dict]:
    t0, seen = time.monotonic(), []
    while True:
        seen.append(httpx.get(f"{base}/v1/jobs/{job_id}").json())
        if seen[-1]["status"] in ("done", "failed"):
            return seen
        assert time.monotonic() - t0 < timeout, seen[-1]
        time.sleep(0.05)


def test_sessions_stream_on_while_an_uploaded_clip_is_made_into_a_style(giant_clip, tmp_path, monkeypatch):
    """The FiLM generator's pass over an uploaded clip runs beside the model's steps, not between
    them: held open here, a session of the same model still gets every frame; only the finished
    style is installed between steps. (Made on the model's step thread, a 15 MiB clip held every
    session's frames up for its whole embedding.)"""
    entered, release = threading.Event(), threading.Event()
    make = type(MODEL).style_from_clip

    def held_open(model, clip):
        entered.set()
        assert release.wait(60), "the test never let the embedding finish"
        return make(model, clip)

    monkeypatch.setattr(type(MODEL), "style_from_clip", held_open)
    body = {"name": "slow-giant", "model": "lpn", "frames": giant_clip, "fps": 30}
    with live_server({"lpn": MODEL}, styles_dir=tmp_path) as (base, _):
        upload: dict = {}
        poster = threading.Thread(
            target=lambda: upload.setdefault(
                "reply", httpx.post(f"{base}/v1/styles", json=body, timeout=UPLOAD_TIMEOUT_S)
            )
        )
        poster.start()
        try:
            assert entered.wait(60), "the upload never reached the clip embedding"
            streamed = drive(base, "normal")  # times out (10 s a frame) if the steps wait for the embedding
        finally:
            release.set()
            poster.join(timeout=60)
        assert len(streamed) == len(WALK) and np.isfinite(streamed).all()
        assert upload["reply"].status_code == 201, upload["reply"].text
        assert "slow-giant" in httpx.get(f"{base}/v1/models").json()[0]["styles"]


def test_fine_tune_job_swaps_in_a_tuned_film_while_a_session_on_the_style_streams_on(giant_clip, tmp_path):
    body = {"name": "tuned-giant", "model": "lpn", "frames": giant_clip, "fps": 30, "fine_tune": True}
    with live_server({"lpn": MODEL}, styles_dir=tmp_path, lpn_fine_tune_steps=STEPS) as (base, app):
        served = app.state.runtime.models["lpn"]
        reply = httpx.post(f"{base}/v1/styles", json=body, timeout=UPLOAD_TIMEOUT_S)
        assert reply.status_code == 201, reply.text  # the style exists at once; the job improves it later
        style, job = reply.json()["style"], reply.json()["job"]
        assert style["status"] == "ready" and style["job_id"] == job["id"] and job["kind"] == "fine_tune"
        instant = film_of(served, "tuned-giant")

        streamer = Streamer(base, "tuned-giant")
        streamer.start()
        seen = poll_job(base, job["id"])
        finished = time.monotonic()
        wait_until(
            lambda: (streamer.replies and streamer.replies[-1][0] > finished) or streamer.error,
            "frames after the swap",
            30,
        )
        streamer.stop.set()
        streamer.join(timeout=10)

        done = seen[-1]
        assert done["status"] == "done", done
        progress = [j["progress"] for j in seen]
        assert progress == sorted(progress) and done["progress"] == 1.0
        assert any(j["status"] == "running" and 0 < j["progress"] < 1 and "loss" in j["message"] for j in seen)
        result = done["result"]
        assert result["installed"] and result["steps"] == STEPS
        assert result["heldout_loss_after"] < result["heldout_loss_before"]

        tuned = film_of(served, "tuned-giant")
        assert np.abs(tuned - instant).max() > 1e-3
        with np.load(tmp_path / "lpn" / "tuned-giant" / "film.npz") as z:
            np.testing.assert_array_equal(z["film"], tuned)
        info = httpx.get(f"{base}/v1/styles/lpn.tuned-giant").json()
        assert info["status"] == "ready" and info["fine_tune"] == result

        assert streamer.error is None, streamer.error
        during = [r for t, r in streamer.replies if t < finished]
        after = [r for t, r in streamer.replies if t > finished]
        assert len(during) > 20 and after and np.isfinite(np.array(during + after)).all()

    with live_server({"lpn": MODEL}, styles_dir=tmp_path) as (
        base,
        app,
    ):  # restarted: the tuned vector, not re-embedded
        np.testing.assert_array_equal(film_of(app.state.runtime.models["lpn"], "tuned-giant"), tuned)
        assert httpx.get(f"{base}/v1/styles/lpn.tuned-giant").json()["fine_tune"] == result
        assert httpx.delete(f"{base}/v1/styles/lpn.tuned-giant").status_code == 204


def wait_stepping(base: str, job_id: str) -> None:
    t0 = time.monotonic()
    while "loss" not in httpx.get(f"{base}/v1/jobs/{job_id}").json()["message"]:
        assert time.monotonic() - t0 < 60
        time.sleep(0.05)


def test_deleting_a_style_or_stopping_the_server_while_a_fine_tune_job_runs_stops_the_job(giant_clip, tmp_path):
    body = {"name": "doomed", "model": "lpn", "frames": giant_clip, "fps": 30, "fine_tune": True}
    with live_server({"lpn": MODEL}, styles_dir=tmp_path, lpn_fine_tune_steps=5000) as (base, app):
        served = app.state.runtime.models["lpn"]
        short = {**body, "frames": {k: v[:90] for k, v in giant_clip.items()}}
        refused = httpx.post(f"{base}/v1/styles", json=short, timeout=UPLOAD_TIMEOUT_S)  # too short to hold frames back
        assert refused.status_code == 422 and refused.json()["code"] == "bad_length", refused.text
        assert httpx.get(f"{base}/v1/styles/lpn.doomed").status_code == 404

        job = httpx.post(f"{base}/v1/styles", json=body, timeout=UPLOAD_TIMEOUT_S).json()["job"]
        wait_stepping(base, job["id"])
        streamer = Streamer(base, "normal")
        streamer.start()
        assert httpx.delete(f"{base}/v1/styles/lpn.doomed").status_code == 204

        failed = poll_job(base, job["id"], timeout=30)[-1]
        assert failed["status"] == "failed" and "deleted" in failed["message"], failed
        assert httpx.get(f"{base}/v1/styles/lpn.doomed").status_code == 404
        assert "doomed" not in served.styles() and not (tmp_path / "lpn" / "doomed").exists()
        again = httpx.post(f"{base}/v1/styles", json={**body, "fine_tune": False}, timeout=UPLOAD_TIMEOUT_S)
        assert again.status_code == 201 and again.json()["job"] is None  # the name is free again
        wait_until(lambda: len(streamer.replies) > 5 or streamer.error, "the streamer's frames", 30)
        streamer.stop.set()
        streamer.join(timeout=10)
        assert streamer.error is None and len(streamer.replies) > 5
        assert httpx.delete(f"{base}/v1/styles/lpn.doomed").status_code == 204

        jobs = app.state.runtime.styles.jobs
        running = httpx.post(f"{base}/v1/styles", json={**body, "name": "cut-short"}, timeout=UPLOAD_TIMEOUT_S).json()[
            "job"
        ]
        wait_stepping(base, running["id"])
    jobs.futures[running["id"]].result(timeout=10)  # the stopped server's job ended within a step
    assert jobs.get(running["id"]).message == "JobStopped: the server is stopping"
