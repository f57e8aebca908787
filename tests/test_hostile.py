"""Hostile but ordinary clients (issue #16), each beside a healthy session whose output must stay
exact: uploads that declare absurd rates or lengths, clips that outgrow their decoding budget,
races on one style name, a disk that refuses the style's files."""

from __future__ import annotations

import concurrent.futures
import contextlib
import json
import shutil

import httpx
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from models.motion import bvh
from models.motion.skeleton import to_bvh
from models.registry import load_models
from models.settings import get_settings

from .cluster import require, shipped_nginx
from .hostile import Bystander, RawClient, RawSocket, ws_url
from .live_server import live_server
from .waiting import wait_until


@pytest.fixture(scope="module")
def models():
    return load_models(get_settings().weights_dir)


@pytest.fixture(scope="module")
def server(models, tmp_path_factory):
    styles_dir = tmp_path_factory.mktemp("styles")
    with live_server(models, styles_dir=styles_dir, idle_timeout_s=30) as (base, app):
        yield base, app, styles_dir


@pytest.fixture(scope="module")
def bystander(server, models, bn_walk):
    """One healthy session for the whole module, checked exact at its end."""
    with Bystander(server[0], bn_walk.slice(0, 120)) as b:
        wait_until(lambda: b.frames() > 5 or b.errors, "the healthy session's first frames", timeout=60)
        yield b
    b.check(models["lti"])


@pytest.fixture(scope="module")
def walk_bvh(bn_walk) -> str:
    return bvh.dumps(to_bvh(bn_walk.slice(0, 120)))


def with_frame_time(text: str, seconds: str) -> str:
    head, _, rest = text.partition("Frame Time:")
    return head + "Frame Time: " + seconds + rest[rest.index("\n") :]


def json_clip(name: str, walk, fps: float, model: str = "lpn") -> dict:
    return {
        "name": name,
        "model": model,
        "fps": fps,
        "frames": {"root": walk.translations[:, 1].tolist(), "rotations": walk.rotations.tolist()},
    }


def longest_bvh(walk, frames: int = 9000) -> str:
    """A BVH of `frames` at 30 fps (default: the longest clip accepted) looping `walk`'s rows."""
    text = bvh.dumps(to_bvh(walk))
    head, _, body = text.partition("Frame Time:")
    time_line, _, rows = body.partition("\n")
    rows = rows.rstrip("\n").split("\n")
    looped = "\n".join(rows[i % len(rows)] for i in range(frames))
    head = head.replace(f"Frames: {walk.num_frames}", f"Frames: {frames}")
    return f"{head}Frame Time:{time_line}\n{looped}\n"


def refused(r: httpx.Response, status: int, code: str) -> None:
    assert r.status_code == status and r.json()["code"] == code, (status, code, r.status_code, r.text[:300])


def test_uploads_declaring_absurd_rates_are_refused_before_any_allocation(models, server, bystander, walk_bvh, bn_walk):
    base = server[0]
    walk = bn_walk.slice(0, 90)
    for seconds in ("10", "1000", "1e300", "0.00001"):
        r = httpx.post(
            f"{base}/v1/styles",
            files={"file": ("w.bvh", with_frame_time(walk_bvh, seconds))},
            data={"name": "slow", "model": "lpn"},
            timeout=30,
        )
        refused(r, 422, "bad_frame_rate")
    for fps in (0.0001, 1e-300):
        refused(httpx.post(f"{base}/v1/styles", json=json_clip("slow", walk, fps), timeout=30), 422, "bad_frame_rate")
    # a legal rate whose clip would be too long once resampled to 30 fps: refused by its declared length
    long_bvh = with_frame_time(walk_bvh, "0.09")  # 120 rows at 11.1 fps = 322 frames at 30 fps
    with live_server(models, upload_max_frames=300) as (small, _):
        r = httpx.post(f"{small}/v1/styles", files={"file": ("w.bvh", long_bvh)}, data={"name": "long", "model": "lpn"})
        refused(r, 422, "bad_length")
        assert "322 frames at 30 fps" in r.json()["message"]


def test_a_clip_beyond_its_decoding_budget_costs_only_its_child(models, bn_walk, walk_bvh, tmp_path):
    """Decoding runs in a child process with a deadline and an address-space cap: a clip that
    needs more gets a typed refusal, and the server goes on serving."""
    long = longest_bvh(bn_walk, 1800)  # 60 s at 30 fps, ~1 MB
    with live_server(models, styles_dir=tmp_path, upload_decode_timeout_s=0.01) as (base, _):
        with Bystander(base, bn_walk.slice(0, 60)) as b:
            r = httpx.post(f"{base}/v1/styles", files={"file": ("w.bvh", long)}, data={"name": "big", "model": "lpn"})
            refused(r, 422, "clip_too_slow")
            wait_until(lambda: b.frames() > 10 or b.errors, "the healthy session streaming on")
        b.check(models["lti"])
    with live_server(models, styles_dir=tmp_path, upload_decode_memory_mb=8) as (base, _):
        r = httpx.post(
            f"{base}/v1/styles", files={"file": ("w.bvh", longest_bvh(bn_walk))}, data={"name": "huge", "model": "lpn"}
        )
        refused(r, 413, "clip_too_large")
        assert httpx.get(f"{base}/healthz").status_code == 200


def test_concurrent_uploads_of_one_name_give_exactly_one_style(server, bystander, bn_walk):
    base = server[0]
    clip = json_clip("twins", bn_walk.slice(0, 90), 30.0)
    with concurrent.futures.ThreadPoolExecutor(6) as pool:
        replies = list(pool.map(lambda _: httpx.post(f"{base}/v1/styles", json=clip, timeout=60), range(6)))
    codes = sorted(r.status_code for r in replies)
    assert codes == [201, 409, 409, 409, 409, 409], [r.text[:200] for r in replies]
    assert all(r.json()["code"] == "style_exists" for r in replies if r.status_code == 409)
    assert httpx.delete(f"{base}/v1/styles/lpn.twins").status_code == 204


def test_a_style_whose_files_cannot_be_written_leaves_no_trace(server, bystander, bn_walk):
    base, _, styles_dir = server
    blocker = styles_dir / ".incoming"  # where a style's files are made before they go live
    shutil.rmtree(blocker, ignore_errors=True)
    blocker.write_text("not a folder: every write under it fails")
    try:
        r = httpx.post(f"{base}/v1/styles", json=json_clip("ghost", bn_walk.slice(0, 90), 30.0), timeout=60)
        refused(r, 507, "storage_full")
        assert "lpn.ghost" not in {s["id"] for s in httpx.get(f"{base}/v1/styles").json()}
        lpn = next(m for m in httpx.get(f"{base}/v1/models").json() if m["name"] == "lpn")
        assert "ghost" not in lpn["styles"]
        refused(httpx.delete(f"{base}/v1/styles/lpn.ghost"), 404, "unknown_style")
    finally:
        blocker.unlink()
    r = httpx.post(f"{base}/v1/styles", json=json_clip("ghost", bn_walk.slice(0, 90), 30.0), timeout=60)
    assert r.status_code == 201, r.text
    assert httpx.delete(f"{base}/v1/styles/lpn.ghost").status_code == 204


def test_the_longest_clip_is_accepted_while_sessions_stream(server, bystander, bn_walk):
    base = server[0]
    before = bystander.frames()
    r = httpx.post(
        f"{base}/v1/styles",
        files={"file": ("w.bvh", longest_bvh(bn_walk))},
        data={"name": "long-walk", "model": "lpn"},
        timeout=120,
    )
    assert r.status_code == 201, r.text
    assert r.json()["style"]["frames"] == 9000
    assert httpx.delete(f"{base}/v1/styles/lpn.long-walk").status_code == 204
    wait_until(lambda: bystander.frames() > before + 3 or bystander.errors, "the healthy session streaming on")


def test_mixes_near_the_float_limit_are_weighed_not_zeroed(models):
    """Weights whose sum overflows used to normalise to all zeros (the input passed through)."""
    from models.interface import style_weights

    huge = style_weights(models["lti"], {"elderly": 1e308, "active": 1e308})
    assert huge == {"elderly": 0.5, "active": 0.5}
    tiny = style_weights(models["lti"], {"elderly": 5e-324, "active": 0.0})
    assert tiny == {"elderly": 1.0, "active": 0.0}
    for bad in ({"elderly": float("nan")}, {"elderly": float("inf")}, {"elderly": 0.0}, {}):
        with pytest.raises(ValueError):
            style_weights(models["lti"], bad)


def start_message(model: str = "lti", style: str = "elderly") -> str:
    return json.dumps({"type": "start", "model": model, "style": style})


def frame_message(seq: int, walk) -> str:
    k = seq % walk.num_frames
    return json.dumps(
        {"type": "frame", "seq": seq, "root": walk.translations[k, 1].tolist(), "rotations": walk.rotations[k].tolist()}
    )


def test_half_open_connections_are_dropped_after_the_header_timeout(models, bn_walk):
    with live_server(models, header_timeout_s=0.3) as (base, _):
        silent, partial = RawSocket(base), RawSocket(base)
        partial.sock.sendall(b"GET /v1/models HTTP/1.1\r\nHost: x\r\n")  # and never the blank line
        assert silent.closed_by_server(timeout=20) and partial.closed_by_server(timeout=20)
        assert httpx.get(f"{base}/healthz").status_code == 200  # an honest request still passes


def test_a_client_that_never_reads_is_freed_within_the_idle_timeout(models, bn_walk):
    """A client that floods frames or resets and then goes quiet without ever reading: the idle
    timeout's error and close cannot be delivered, so after send_timeout_s more the connection is
    aborted and its session freed, where before the error's send waited for ever."""
    with live_server(models, idle_timeout_s=1.5, send_timeout_s=0.5, max_messages_per_s=1e5) as (base, app):
        runtime = app.state.runtime
        with Bystander(base, bn_walk.slice(0, 60)) as b:
            wait_until(lambda: len(runtime.connections) == 1, "the healthy session")
            for flood in ("frames", "resets"):
                client = RawClient(base)
                client.send_text(start_message())
                client.sock.settimeout(5.0)  # the server stops reading once its replies back up
                try:
                    for seq in range(3000):
                        client.send_text(frame_message(seq, bn_walk) if flood == "frames" else '{"type": "reset"}')
                except OSError:  # timed out or reset: the server is not taking more
                    pass
                wait_until(lambda: len(runtime.connections) == 1, f"the non-reading client ({flood}) freed", 30)
                assert client.closed_by_server(timeout=20)
                client.close()
            assert b.frames() > 0
        b.check(models["lti"])


def test_a_flooding_client_is_told_then_closed(models, bn_walk):
    """Over the per-connection message rate: dropped, a typed `rate_limited` error at the start of
    each run over it, and a run a second's worth long closes the connection (1008)."""
    with live_server(models, max_messages_per_s=100) as (base, _):
        with Bystander(base, bn_walk.slice(0, 60)) as b:
            received = []
            with connect(ws_url(base)) as ws:
                ws.send(start_message())
                assert json.loads(ws.recv(timeout=10))["type"] == "started"
                with contextlib.suppress(ConnectionClosed):  # it may close while these are still going out
                    for seq in range(2000):
                        ws.send(frame_message(seq, bn_walk))
                with pytest.raises(ConnectionClosed) as closed:
                    while True:  # what came back before the close, then the close
                        received.append(json.loads(ws.recv(timeout=20)))
            assert closed.value.rcvd is not None and closed.value.rcvd.code == 1008, closed.value
            errors = [m["code"] for m in received if m["type"] == "error"]
            assert set(errors) == {"rate_limited"} and len(errors) >= 2, (
                errors
            )  # told (each run over), then why it closed
            assert sum(m["type"] == "frame" for m in received) >= 1
        b.check(models["lti"])


def test_a_forged_forwarded_for_changes_nothing_through_the_shipped_proxy(models, tmp_path):
    """Behind docker/nginx.conf, with X-Forwarded-For trusted from the proxy's address only (as
    compose sets it), a client naming another address in its own header is still counted as
    itself: its second session hits its cap of one."""
    require("nginx")
    with (
        live_server(models, token_max_sessions=1, uvicorn_options={"forwarded_allow_ips": "127.0.0.1"}) as (base, _),
        shipped_nginx(tmp_path, [int(base.rsplit(":", 1)[1])]) as proxy,
    ):
        url = ws_url(proxy)
        with connect(url, additional_headers={"X-Forwarded-For": "203.0.113.7"}) as first:
            first.send(start_message())
            assert json.loads(first.recv(timeout=10))["type"] == "started"
            with connect(url, additional_headers={"X-Forwarded-For": "198.51.100.9"}) as second:
                second.send(start_message())
                refusal = json.loads(second.recv(timeout=10))
                assert refusal["type"] == "error" and refusal["code"] == "too_many_sessions", refusal
