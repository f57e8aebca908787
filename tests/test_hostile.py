"""Hostile but ordinary clients (issue #16), each beside a healthy session whose output must stay
exact: uploads that declare absurd rates or lengths, clips that outgrow their decoding budget,
races on one style name, a disk that refuses the style's files."""

from __future__ import annotations

import concurrent.futures
import contextlib
import json
import shutil

import httpx
import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

from clients.raw_ws import RawClient, RawSocket
from models.motion import bvh
from models.motion.skeleton import to_bvh
from models.registry import load_models
from models.settings import get_settings
from service.transport import FLOOD_LINGER_MAX_BYTES

from .cluster import require, shipped_nginx
from .hostile import Bystander, json_clip, longest_bvh
from .live_server import UPLOAD_TIMEOUT_S, live_server, ws_url
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
        yield b
    b.check(models["lti"])


@pytest.fixture(scope="module")
def walk_bvh(bn_walk) -> str:
    return bvh.dumps(to_bvh(bn_walk.slice(0, 120)))


def with_frame_time(text: str, seconds: str) -> str:
    head, _, rest = text.partition("Frame Time:")
    return head + "Frame Time: " + seconds + rest[rest.index("\n") :]


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
            timeout=UPLOAD_TIMEOUT_S,
        )
        refused(r, 422, "bad_frame_rate")
    for fps in (0.0001, 1e-300):
        refused(
            httpx.post(f"{base}/v1/styles", json=json_clip("slow", walk, fps), timeout=UPLOAD_TIMEOUT_S),
            422,
            "bad_frame_rate",
        )
    # a legal rate whose clip would be too long once resampled to 30 fps: refused by its declared length
    long_bvh = with_frame_time(walk_bvh, "0.09")  # 120 rows at 11.1 fps = 322 frames at 30 fps
    with live_server(models, upload_max_frames=300) as (small, _):
        r = httpx.post(
            f"{small}/v1/styles",
            files={"file": ("w.bvh", long_bvh)},
            data={"name": "long", "model": "lpn"},
            timeout=UPLOAD_TIMEOUT_S,
        )
        refused(r, 422, "bad_length")
        assert "322 frames at 30 fps" in r.json()["message"]


def test_a_clip_beyond_its_decoding_budget_costs_only_its_child(models, bn_walk, walk_bvh, tmp_path):
    """Decoding runs in a child process with a deadline and an address-space cap: a clip that
    needs more gets a typed refusal, and the server goes on serving."""
    long = longest_bvh(bn_walk, 1800)  # 60 s at 30 fps, ~1 MB
    with live_server(models, styles_dir=tmp_path, upload_decode_cpu_s=0.01) as (base, _):
        with Bystander(base, bn_walk.slice(0, 60)) as b:
            r = httpx.post(
                f"{base}/v1/styles",
                files={"file": ("w.bvh", long)},
                data={"name": "big", "model": "lpn"},
                timeout=UPLOAD_TIMEOUT_S,
            )
            refused(r, 422, "clip_too_slow")
            wait_until(lambda: b.frames() > 10 or b.errors, "the healthy session streaming on")
        b.check(models["lti"])
    with live_server(models, styles_dir=tmp_path, upload_decode_memory_mb=8) as (base, _):
        r = httpx.post(
            f"{base}/v1/styles",
            files={"file": ("w.bvh", longest_bvh(bn_walk))},
            data={"name": "huge", "model": "lpn"},
            timeout=UPLOAD_TIMEOUT_S,
        )
        refused(r, 413, "clip_too_large")
        assert httpx.get(f"{base}/healthz").status_code == 200


def test_concurrent_uploads_of_one_name_give_exactly_one_style(server, bystander, bn_walk):
    base = server[0]
    clip = json_clip("twins", bn_walk.slice(0, 90), 30.0)
    with concurrent.futures.ThreadPoolExecutor(6) as pool:
        replies = list(
            pool.map(lambda _: httpx.post(f"{base}/v1/styles", json=clip, timeout=UPLOAD_TIMEOUT_S), range(6))
        )
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
        r = httpx.post(
            f"{base}/v1/styles", json=json_clip("ghost", bn_walk.slice(0, 90), 30.0), timeout=UPLOAD_TIMEOUT_S
        )
        refused(r, 507, "storage_full")
        assert "lpn.ghost" not in {s["id"] for s in httpx.get(f"{base}/v1/styles").json()}
        lpn = next(m for m in httpx.get(f"{base}/v1/models").json() if m["name"] == "lpn")
        assert "ghost" not in lpn["styles"]
        refused(httpx.delete(f"{base}/v1/styles/lpn.ghost"), 404, "unknown_style")
    finally:
        blocker.unlink()
    r = httpx.post(f"{base}/v1/styles", json=json_clip("ghost", bn_walk.slice(0, 90), 30.0), timeout=UPLOAD_TIMEOUT_S)
    assert r.status_code == 201, r.text
    assert httpx.delete(f"{base}/v1/styles/lpn.ghost").status_code == 204


def test_the_longest_clip_is_accepted_while_sessions_stream(server, bystander, bn_walk):
    base = server[0]
    before = bystander.frames()
    r = httpx.post(
        f"{base}/v1/styles",
        files={"file": ("w.bvh", longest_bvh(bn_walk))},
        data={"name": "long-walk", "model": "lpn"},
        timeout=UPLOAD_TIMEOUT_S,
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


def test_header_deadlines_are_spread_so_a_burst_is_not_dropped_at_once(monkeypatch):
    """Each connection's deadline lies in [timeout, 1.5 x timeout): 2,000 half-open connections
    opened together used to be aborted in one pass of the event loop."""
    from service import transport

    armed = []

    class Loop:
        def call_later(self, delay, callback):
            armed.append(delay)
            return None

    http = transport.GuardedHttp.__new__(transport.GuardedHttp)
    http.loop, http._header_timer, http.header_timeout_s = Loop(), None, 10.0
    for _ in range(2000):
        http._arm_header_timer()
    assert 10.0 <= min(armed) and max(armed) < 15.0
    assert np.ptp(armed) > 4.0 and len(set(armed)) > 1900  # spread over the window, not a few instants


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
                # up to 3,000 frames fit in the server's socket buffers and are each stepped before the
                # idle timeout can start: on a loaded machine that backlog alone once took over 30 s
                wait_until(lambda: len(runtime.connections) == 1, f"the non-reading client ({flood}) freed", 120)
                assert client.closed_by_server(timeout=20)
                client.close()
            assert b.frames() > 0
        b.check(models["lti"])


def test_a_flooding_client_is_told_then_closed(models, bn_walk):
    """Over the per-connection message rate: dropped, a typed `rate_limited` error, and a second's
    worth dropped before the client calms down closes the connection (4429)."""
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
            assert closed.value.rcvd is not None and closed.value.rcvd.code == 4429, closed.value
            errors = [m["code"] for m in received if m["type"] == "error"]
            assert set(errors) == {"rate_limited"} and len(errors) >= 2, (
                errors
            )  # told (each run over), then why it closed
            assert sum(m["type"] == "frame" for m in received) >= 1
        b.check(models["lti"])


def test_a_client_closed_for_flooding_can_still_send_and_then_reads_the_close(models, bn_walk):
    """A flood script is usually still writing when it is closed, and a client library may not
    read the close until its write returns (the websockets sync client holds its lock while a send
    blocks). So after the 4429 close the server goes on taking what the client sends (here 32 MiB
    more, beyond what the kernel buffers would hold) and ends the stream cleanly after the close
    frame. Before, it stopped reading and reset the connection a second later: the flooder's sends
    blocked, and it could see 1006 instead of 4429."""
    with live_server(models, max_messages_per_s=100) as (base, _):
        with Bystander(base, bn_walk.slice(0, 60)) as b:
            client = RawClient(base, rcvbuf=1 << 20)
            client.send_text(start_message())
            client.sock.settimeout(20.0)
            frame = client.text_frame(frame_message(0, bn_walk))
            for _ in range(2000 + (32 << 20) // len(frame)):  # the flood, then 32 MiB more, unread
                client.sock.sendall(frame)
            opcodes = []
            with contextlib.suppress(EOFError):
                while True:
                    opcode, payload = client.recv_frame()
                    opcodes.append(opcode)
            assert opcodes[0] == 0x1 and opcodes[-1] == 0x8, opcodes  # replies, then the close
            assert int.from_bytes(payload[:2], "big") == 4429
            client.close()
        b.check(models["lti"])


def test_a_flooding_client_that_reconnects_is_refused_while_it_cools_down(models, bn_walk):
    """A flood script reconnects at once; each new connection would cost the server another
    burst read before the close. Its caller's handshakes are refused (HTTP 429 `rate_limited`,
    Retry-After) for flood_cooldown_s; a session it already had open goes on, exact.

    The flood is 5,000 frames, within what the server drains after the close: this client's reader
    thread cannot take the close in while its sender holds the connection lock, and on a loaded
    machine it was starved through 64 MiB of sends (reset: 1006, not 4429) of a 100,000-frame one."""
    flood = [frame_message(seq, bn_walk) for seq in range(5000)]
    assert sum(map(len, flood)) < FLOOD_LINGER_MAX_BYTES // 2
    with live_server(models, max_messages_per_s=100, flood_cooldown_s=600) as (base, _):
        with Bystander(base, bn_walk.slice(0, 60)) as b:  # the same address as the flooder
            with connect(ws_url(base)) as ws:
                ws.send(start_message())
                assert json.loads(ws.recv(timeout=10))["type"] == "started"
                with contextlib.suppress(ConnectionClosed):  # sends fail once it is closed
                    for frame in flood:
                        ws.send(frame)
                    while True:
                        ws.recv(timeout=20)
            assert ws.close_code == 4429
            with pytest.raises(InvalidStatus) as refused:
                connect(ws_url(base))
            response = refused.value.response
            assert response.status_code == 429 and 590 <= int(response.headers["Retry-After"]) <= 600
            assert json.loads(response.body)["code"] == "rate_limited"
            assert "closed for flooding" in json.loads(response.body)["message"]
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


# ---- tenants -------------------------------------------------------------------------------------

A, B, ADMIN = "tenant-a-token", "tenant-b-token", "admin-token"


def bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


@pytest.fixture(scope="module")
def tenants(models, tmp_path_factory):
    with live_server(
        models,
        styles_dir=tmp_path_factory.mktemp("tenant-styles"),
        api_tokens=[A, B, ADMIN],
        admin_tokens=[ADMIN],
        token_max_stored_sessions=2,
    ) as (base, app):
        yield base, app


def start_reply(base: str, token: str, **start) -> dict:
    """Open a session as `token` (lti, elderly unless `start` says otherwise), and close it: the
    server's reply to the start message."""
    with connect(ws_url(base), additional_headers=bearer(token)) as ws:
        ws.send(json.dumps({"type": "start", "model": "lti", "style": "elderly", **start}))
        return json.loads(ws.recv(timeout=20))


def test_uploaded_styles_belong_to_their_tenant(tenants, bn_walk):
    base, _ = tenants
    r = httpx.post(
        f"{base}/v1/styles",
        json=json_clip("mine", bn_walk.slice(0, 90), 30.0),
        headers=bearer(A),
        timeout=UPLOAD_TIMEOUT_S,
    )
    assert r.status_code == 201, r.text
    ids = {t: {s["id"] for s in httpx.get(f"{base}/v1/styles", headers=bearer(t)).json()} for t in (A, B, ADMIN)}
    assert "lpn.mine" in ids[A] and "lpn.mine" in ids[ADMIN] and "lpn.mine" not in ids[B]
    assert "lpn.elderly" in ids[B]  # trained styles are everyone's
    refused(httpx.get(f"{base}/v1/styles/lpn.mine", headers=bearer(B)), 404, "unknown_style")
    refused(httpx.delete(f"{base}/v1/styles/lpn.mine", headers=bearer(B)), 404, "unknown_style")
    lpn_for = {
        t: next(m for m in httpx.get(f"{base}/v1/models", headers=bearer(t)).json() if m["name"] == "lpn")
        for t in (A, B)
    }
    assert "mine" in lpn_for[A]["styles"] and "mine" not in lpn_for[B]["styles"]
    assert start_reply(base, A, model="lpn", style="mine")["type"] == "started"
    assert start_reply(base, B, model="lpn", style="mine")["code"] == "unknown_style"
    with connect(ws_url(base), additional_headers=bearer(B)) as ws:  # nor can a running session switch to it
        ws.send(json.dumps({"type": "start", "model": "lpn", "style": "elderly"}))
        assert json.loads(ws.recv(timeout=20))["type"] == "started"
        ws.send(json.dumps({"type": "style", "mix": {"elderly": 0.5, "mine": 0.5}}))
        assert json.loads(ws.recv(timeout=20))["code"] == "unknown_style"
    assert httpx.delete(f"{base}/v1/styles/lpn.mine", headers=bearer(ADMIN)).status_code == 204


def test_only_the_tenant_that_opened_a_session_may_resume_it(tenants):
    base, _ = tenants
    reply = start_reply(base, A)
    token = reply["resume_token"]
    refusal = start_reply(base, B, resume_token=token)
    assert refusal["type"] == "error" and refusal["code"] == "unknown_resume_token", refusal
    resumed = start_reply(base, A, resume_token=token)
    assert resumed["type"] == "started" and resumed["session_id"] == reply["session_id"]


def test_a_callers_closed_sessions_are_capped_without_touching_anothers(tenants):
    base, app = tenants
    runtime = app.state.runtime
    b_reply = start_reply(base, B)
    a_tokens = []
    for _ in range(3):  # A's cap is 2: its first is forgotten
        reply = start_reply(base, A)
        a_tokens.append(reply["resume_token"])
        wait_until(lambda s=reply["session_id"]: s not in runtime.sessions, "the session closed")
    for token, caller, want in (
        (a_tokens[0], A, "error"),
        (a_tokens[2], A, "started"),
        (b_reply["resume_token"], B, "started"),
    ):
        reply = start_reply(base, caller, resume_token=token)
        assert reply["type"] == want, (want, reply)


def test_failed_authentication_is_rate_limited_per_address(tenants):
    base, app = tenants
    limiter = app.state.limiter
    # the limiter's clock stands still while the guesses go out, so a slow, loaded machine, whose
    # requests take longer than the refill period, sees the same counts as a fast one
    real_clock = limiter.clock
    frozen = real_clock()
    limiter.clock = lambda: frozen
    try:
        codes = [httpx.get(f"{base}/v1/styles", headers=bearer(f"guess-{i}")).status_code for i in range(12)]
        assert codes[:10] == [401] * 10 and codes[10:] == [429, 429], codes
        assert httpx.get(f"{base}/v1/styles", headers=bearer(A)).status_code == 429  # until the address cools down
    finally:
        limiter.clock = real_clock
    wait_until(lambda: httpx.get(f"{base}/healthz").status_code == 200, "health, which needs no token")


def test_tokens_never_reach_the_logs():
    import logging

    from service.logs import RedactTokens

    record = logging.LogRecord(
        "uvicorn.access",
        logging.INFO,
        "",
        0,
        '%s - "%s %s HTTP/%s" %d',
        ("1.2.3.4", "GET", "/v1/stream?model=x&token=s3cret", "1.1", 101),
        None,
    )
    RedactTokens().filter(record)
    assert "s3cret" not in record.getMessage() and "token=***" in record.getMessage()
    from clients.sdk_wire import auth_headers
    from clients.sdk_wire import ws_url as sdk_ws_url

    assert "token" not in sdk_ws_url("http://h:1") and auth_headers("t") == {"Authorization": "Bearer t"}


def test_new_sessions_faster_than_the_callers_rate_are_refused(models):
    with live_server(models, token_sessions_per_s=2, token_max_sessions=3) as (base, _):
        replies = []
        for _ in range(6):
            with connect(ws_url(base)) as ws:
                ws.send(start_message())
                replies.append(json.loads(ws.recv(timeout=20)))
        kinds = [r["type"] if r["type"] == "started" else r["code"] for r in replies]
        assert kinds[:3] == ["started"] * 3 and "too_many_sessions" in kinds[3:], kinds


def test_style_and_reset_messages_have_their_own_lower_rate(models, bn_walk):
    """Each reset or style change costs a model reset or a reply: past max_controls_per_s they
    are dropped (told once), and a second's worth more closes the connection; frames still flow."""
    with live_server(models, max_controls_per_s=5) as (base, _):
        received = []
        with connect(ws_url(base)) as ws:
            ws.send(start_message())
            assert json.loads(ws.recv(timeout=10))["type"] == "started"
            for _ in range(7):  # 5 pass (the burst), the 6th is told, the 7th dropped
                ws.send('{"type": "reset"}')
            ws.send(frame_message(0, bn_walk))
            while not received or received[-1]["type"] != "frame":
                received.append(json.loads(ws.recv(timeout=20)))
            with contextlib.suppress(ConnectionClosed):  # it may close while these are still going out
                for _ in range(10):
                    ws.send('{"type": "reset"}')
            with pytest.raises(ConnectionClosed) as closed:
                while True:  # what came back before the close, then the close
                    received.append(json.loads(ws.recv(timeout=20)))
        assert closed.value.rcvd is not None and closed.value.rcvd.code == 4429
        kinds = [m["type"] if m["type"] != "error" else m["code"] for m in received]
        assert 5 <= kinds.count("reset_done") <= 6 and kinds.count("rate_limited") == 2, kinds
