"""The Python SDK against a real server: sync and asyncio sessions, style changes, errors, the REST
calls (styles, uploads, jobs), timeouts set by the caller, closing."""

from __future__ import annotations

import asyncio
import json
import re
import socket
import threading
import time
from contextlib import contextmanager

import httpx
import numpy as np
import pytest

from clients.cli import main as cli_main
from clients.sdk import AsyncClient, Client, JobInfo, NothingInFlight, ReplyTimeout, ServerError, StyleInfo
from models.data import select
from models.registry import load_models
from models.settings import get_settings

from .live_server import live_server


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    with live_server(load_models(get_settings().weights_dir), styles_dir=tmp_path_factory.mktemp("styles")) as (url, _):
        yield url


def test_sync_session_streams_and_switches_style(base, bn_walk):
    client = Client(base)
    assert {m.name for m in client.models()} >= {"lti", "erd"}
    root, rot = bn_walk.translations[:20, 1], bn_walk.rotations[:20]
    with client.session(model="lti", style="elderly") as session:
        frames = [session.stylise(root[t], rot[t]) for t in range(10)]
        ack = session.set_style("exhausted", transition_frames=5)
        assert ack["type"] == "style_set"
        frames += [session.stylise(root[t], rot[t]) for t in range(10, 20)]
    assert [f.seq for f in frames] == list(range(20))
    assert all(f.rotations.shape == (22, 4) and np.isfinite(f.root).all() for f in frames)


def test_async_session_gives_the_same_frames_as_sync(base, bn_walk):
    root, rot = bn_walk.translations[:8, 1], bn_walk.rotations[:8]
    with Client(base).session(model="erd", style="elderly") as session:
        sync = [session.stylise(root[t], rot[t]).rotations for t in range(8)]

    async def run():
        async with AsyncClient(base).session(model="erd", style="elderly") as session:
            return [(await session.stylise(root[t], rot[t])).rotations for t in range(8)]

    np.testing.assert_allclose(np.array(asyncio.run(run())), np.array(sync), atol=1e-6)


def test_server_errors_become_typed_exceptions(base):
    with pytest.raises(ServerError) as err:
        Client(base).session(model="lti", style="no-such-style")
    assert err.value.code == "unknown_style"
    with Client(base).session(model="lti", style="elderly") as session:
        with pytest.raises(ServerError) as err:
            session.set_style("no-such-style")
        assert err.value.code == "unknown_style"
        session.reset()  # the session lives on


def test_session_resumes_by_itself_after_the_connection_drops(base, bn_walk):
    """The socket dies mid-stream; the next stylise() reconnects with the resume token and the
    outputs equal an uninterrupted run."""
    root, rot = bn_walk.translations[:30, 1], bn_walk.rotations[:30]
    with Client(base).session(model="lti", style="elderly") as session:
        whole = [session.stylise(root[t], rot[t]).rotations for t in range(30)]
    with Client(base).session(model="lti", style="elderly") as session:
        first = [session.stylise(root[t], rot[t]).rotations for t in range(15)]
        token = session.resume_token
        session.ws.close()  # the connection drops
        rest = [session.stylise(root[t], rot[t]).rotations for t in range(15, 30)]
        assert session.resume_token == token and session.info["last_seq"] == 14
        assert session.reconnects == 1 and session.last_reconnect.kind == "resumed"
    np.testing.assert_allclose(np.array(first + rest), np.array(whole), atol=1e-6)


# ---- REST ------------------------------------------------------------------------------------


def test_styles_are_listed_and_read(base):
    with Client(base) as client:
        styles = client.styles(model="lti")
        assert {s.id for s in styles} >= {"lti.elderly", "lti.exhausted"} and all(s.model == "lti" for s in styles)
        one = client.style("lti.elderly")
        assert isinstance(one, StyleInfo) and (one.kind, one.status) == ("trained", "ready")
        with pytest.raises(ServerError) as err:
            client.style("lti.no-such-style")
        assert (err.value.status, err.value.code) == (404, "unknown_style")


def test_a_bvh_upload_is_fine_tuned_followed_to_the_end_used_and_deleted(base, index, bn_walk):
    """Multipart BVH upload with fine_tune: `wait_job` reports progress until done, the style
    streams, `delete_style` removes it."""
    clip = select(index, dataset="bandai-namco-2", style="elderly", content="walk", split="test")[0]
    seen: list[JobInfo] = []
    with Client(base) as client:
        upload = client.upload_style("sdk-elderly", model="lti", bvh=clip.path, fine_tune=True)
        assert upload.style.id == "lti.sdk-elderly" and upload.job is not None and not upload.created
        done = client.wait_job(upload.job.id, progress=seen.append, timeout=300)
        assert done.status == "done" and done.progress == 1.0 and done.target == "lti.sdk-elderly"
        assert seen[-1] == done and [j.progress for j in seen] == sorted(j.progress for j in seen)
        assert client.style("lti.sdk-elderly").status == "ready"
        with client.session(model="lti", style="sdk-elderly") as session:
            frame = session.stylise(bn_walk.translations[0, 1], bn_walk.rotations[0])
            assert np.isfinite(frame.rotations).all()
        client.delete_style("lti.sdk-elderly")
        assert "lti.sdk-elderly" not in {s.id for s in client.styles()}
        with pytest.raises(ServerError) as err:
            client.delete_style("lti.sdk-elderly")
        assert err.value.status == 404


def test_add_style_follows_every_job_and_reports_each_models_answer(base, index, bn_walk):
    """One call uploads to several models and follows every job to the end: Style-ERD's style is
    live when its upload returns, LTI's when its identification job ends. Style-ERD's job pairs
    the clip with neutral clips from the mocap, so it needs no prebuilt feature cache."""
    clip = select(index, dataset="bandai-namco-1", style="proud", content="walk")[0]
    seen: list[tuple[str, JobInfo]] = []
    with Client(base) as client:
        added = client.add_style(
            "sdk-proud", models=["lti", "erd"], bvh=clip.path, progress=lambda m, j: seen.append((m, j))
        )
        lti, erd = added["lti"], added["erd"]
        assert lti.error is None and lti.style is not None and lti.style.status == "ready"
        assert lti.live_s is not None and lti.done_s is not None and 0 < lti.live_s <= lti.done_s
        last = dict(seen)  # each model's last report
        assert all(j.status == "done" for j in last.values())
        client.delete_style("lti.sdk-proud")
        assert last.keys() == {"lti", "erd"}
        assert erd.error is None and erd.style is not None and erd.style.status == "ready"
        assert erd.live_s is not None and erd.done_s is not None and 0 < erd.live_s <= erd.done_s
        root, rot = bn_walk.translations[:10, 1], bn_walk.rotations[:10]
        with client.session(model="erd", style="sdk-proud") as session:  # the fitted branch streams
            frames = [session.stylise(root[t], rot[t]) for t in range(10)]
        assert all(np.isfinite(f.rotations).all() for f in frames)
        client.delete_style("erd.sdk-proud")


def test_styles_add_on_the_command_line_says_when_each_style_went_live(base, index, capsys):
    clip = select(index, dataset="bandai-namco-1", style="proud", content="walk")[0]
    server = ["--url", base]
    assert (
        cli_main(["styles", "add", str(clip.path), "--name", "cli-proud", "--model", "lpn", "--no-fine-tune", *server])
        == 0
    )
    assert re.search(r"^lpn  lpn\.cli-proud: ready, live after \d+\.\d s$", capsys.readouterr().out, re.M)
    assert (
        cli_main(["styles", "add", str(clip.path), "--name", "cli-proud", "--model", "erd", "--no-fine-tune", *server])
        == 0
    )
    assert re.search(r"^erd  erd\.cli-proud: ready, live after \d+\.\d s$", capsys.readouterr().out, re.M)
    assert cli_main(["styles", "list", "--model", "lpn", *server]) == 0
    assert re.search(r"^lpn\.cli-proud +uploaded +ready$", capsys.readouterr().out, re.M)
    assert cli_main(["styles", "rm", "lpn.cli-proud", *server]) == 0
    assert cli_main(["styles", "rm", "erd.cli-proud", *server]) == 0
    with Client(base) as client:
        assert "lpn.cli-proud" not in {s.id for s in client.styles()}


def test_a_frames_upload_says_what_is_wrong_with_it(base, bn_walk):
    root, rot = bn_walk.translations[:90, 1], bn_walk.rotations[:90]
    with Client(base) as client, pytest.raises(ServerError) as err:
        client.upload_style("no-job", model="lti", frames=(root, rot))  # LTI styles need fine_tune
    assert (err.value.status, err.value.code) == (422, "fine_tune_required")
    with pytest.raises(ValueError):
        Client(base).upload_style("both", bvh="HIERARCHY", frames=(root, rot))


def test_the_async_client_lists_and_follows_jobs(base):
    async def run():
        async with AsyncClient(base, timeout=10) as client:
            styles = await client.styles()
            with pytest.raises(ServerError) as err:
                await client.wait_job("no-such-job")
            return styles, err.value

    styles, err = asyncio.run(run())
    assert any(s.id == "erd.elderly" for s in styles) and (err.status, err.code) == (404, "unknown_job")


# ---- timeouts and closing --------------------------------------------------------------------


@contextmanager
def silent_stream_server():
    """A WebSocket endpoint that opens sessions and then never answers a frame."""
    from websockets.sync.server import serve

    def handler(ws) -> None:
        json.loads(ws.recv())
        ws.send(
            json.dumps(
                {"type": "started", "session_id": "s", "resume_token": "t", "joints": ["j"] * 22, "last_seq": None}
            )
        )
        for _ in ws:
            pass

    with serve(handler, "127.0.0.1", 0) as server:
        thread = threading.Thread(target=server.serve_forever, daemon=True)
        thread.start()
        yield f"http://127.0.0.1:{server.socket.getsockname()[1]}"
        server.shutdown()
    thread.join(timeout=10)


def test_timeouts_are_the_callers_sync_and_asyncio(bn_walk):
    root, rot = bn_walk.translations[0, 1], bn_walk.rotations[0]
    with silent_stream_server() as url:
        with Client(url, timeout=0.3).session(model="lti", style="elderly") as session:
            t0 = time.monotonic()
            with pytest.raises(ReplyTimeout):
                session.stylise(root, rot)
            assert 0.25 < time.monotonic() - t0 < 5
            session.send(root, rot)
            with pytest.raises(TimeoutError):  # a built-in TimeoutError too
                session.receive(timeout=0.1)
        with Client(url).session(model="lti", style="elderly") as idle, pytest.raises(NothingInFlight):
            idle.receive()

        async def run() -> float:
            async with AsyncClient(url, timeout=0.3) as client:
                async with client.session(model="lti", style="elderly") as session:
                    t0 = time.monotonic()
                    with pytest.raises(ReplyTimeout):
                        await session.stylise(root, rot)
                    return time.monotonic() - t0

        assert 0.25 < asyncio.run(run()) < 5

    with socket.create_server(("127.0.0.1", 0)) as hung:  # accepts, never answers
        url = f"http://127.0.0.1:{hung.getsockname()[1]}"
        t0 = time.monotonic()
        with pytest.raises(httpx.TimeoutException):
            Client(url, timeout=0.3).models()
        assert time.monotonic() - t0 < 5


def test_closing_the_client_ends_its_sessions(base, bn_walk):
    with Client(base) as client:
        session = client.session(model="lti", style="elderly")
        session.stylise(bn_walk.translations[0, 1], bn_walk.rotations[0])
    assert session.core.closed and client.http.is_closed
    with pytest.raises(RuntimeError, match="closed"):
        session.stylise(bn_walk.translations[1, 1], bn_walk.rotations[1])
