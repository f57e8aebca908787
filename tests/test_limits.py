"""Per-token limits on a real server: concurrent sessions (1013), REST request rate (429 with
Retry-After), upload size (413); each token's limits are its own, and anonymous callers get the
defaults keyed by their address."""

from __future__ import annotations

import json
import time

import httpx
import pytest
from pydantic import ValidationError
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from models.registry import load_models
from models.settings import get_settings
from service.api import ApiError
from service.limits import Bucket, take
from service.settings import ServiceSettings

from .live_server import UPLOAD_TIMEOUT_S, live_server

RATED, CAPPED, OTHER = "tok-rated", "tok-capped", "tok-other"
LIMITS = {RATED: {"requests_per_s": 1, "burst_s": 3}, CAPPED: {"max_sessions": 2, "upload_max_bytes": 2000}}


@pytest.fixture(scope="module")
def models():
    return {"lti": load_models(get_settings().weights_dir)["lti"]}


@pytest.fixture(scope="module")
def server(models):
    with live_server(models, api_tokens=[RATED, CAPPED, OTHER], token_limits=LIMITS) as (base, app):
        yield base, app


def auth(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def stream_url(base: str, token: str) -> str:
    return base.replace("http", "ws") + f"/v1/stream?token={token}"


def start(ws) -> dict:
    ws.send(json.dumps({"type": "start", "model": "lti", "style": "elderly"}))
    return json.loads(ws.recv(timeout=10))


def assert_refused_with_1013(ws) -> None:
    error = start(ws)
    assert error["type"] == "error" and error["code"] == "too_many_sessions", error
    with pytest.raises(ConnectionClosed) as closed:
        ws.recv(timeout=10)
    assert closed.value.rcvd.code == 1013


# ---- the token bucket ------------------------------------------------------------------------


def test_a_bucket_lets_a_burst_through_then_refills_at_the_rate():
    bucket, passed = None, 0
    for _ in range(5):
        bucket, wait = take(bucket, now=10.0, rate=2.0, burst=3.0)
        passed += wait == 0
    assert passed == 3
    assert take(bucket, now=10.0, rate=2.0, burst=3.0)[1] == pytest.approx(0.5)  # one request back in 1/rate s
    assert take(bucket, now=10.5, rate=2.0, burst=3.0)[1] == 0
    refilled, _ = take(Bucket(0.0, 0.0), now=100.0, rate=2.0, burst=3.0)
    assert refilled.tokens == pytest.approx(2.0)  # capped at the burst, less the request just taken


def test_buckets_of_callers_gone_quiet_are_forgotten():
    """Anonymous callers are keyed by address; the limiter must not grow with every address it saw."""
    from service import limits

    now = [0.0]
    limiter = limits.Limiter(ServiceSettings(token_requests_per_s=1, token_burst_s=2), clock=lambda: now[0])
    for i in range(limits.MAX_IDLE_BUCKETS):
        limiter.check_request(limiter.identify(None, None, f"10.0.{i // 256}.{i % 256}"))
    now[0] = 10.0  # every bucket has refilled
    busy = limiter.identify(None, None, "10.9.9.8")
    limiter.check_request(busy)
    limiter.check_request(busy)  # its burst of 2 is spent
    assert set(limiter.buckets) == {busy.key}  # the rest refilled and were forgotten
    with pytest.raises(ApiError):  # and what was spent is not forgotten with them
        limiter.check_request(busy)


def test_a_caller_closed_for_flooding_cools_down_alone_and_for_its_cooldown_only():
    from service import limits

    now = [0.0]
    limiter = limits.Limiter(ServiceSettings(flood_cooldown_s=10), clock=lambda: now[0])
    flooder, other = limiter.identify(None, None, "10.0.0.1"), limiter.identify(None, None, "10.0.0.2")
    limiter.flooded(flooder)
    now[0] = 9.5
    assert limiter.cooldown_left(flooder) == pytest.approx(0.5)
    assert limiter.cooldown_left(other) == 0.0
    now[0] = 10.0
    assert limiter.cooldown_left(flooder) == 0.0 and not limiter.cooling  # forgotten once over


def test_no_flood_cooldown_when_it_is_set_to_zero():
    from service import limits

    limiter = limits.Limiter(ServiceSettings(flood_cooldown_s=0))
    flooder = limiter.identify(None, None, "10.0.0.1")
    limiter.flooded(flooder)
    assert limiter.cooldown_left(flooder) == 0.0


# ---- settings --------------------------------------------------------------------------------


def test_per_token_limits_come_from_the_environment(monkeypatch):
    monkeypatch.setenv("STYLESTREAM_API_TOKENS", json.dumps(["tok-a", "tok-b"]))
    monkeypatch.setenv("STYLESTREAM_TOKEN_LIMITS", json.dumps({"tok-a": {"max_sessions": 4, "requests_per_s": 5}}))
    from service.limits import Limiter

    limiter = Limiter(ServiceSettings())
    a, b = limiter.limits_for("tok-a"), limiter.limits_for("tok-b")
    assert (a.max_sessions, a.requests_per_s) == (4, 5.0)
    assert a.upload_max_bytes == b.upload_max_bytes == ServiceSettings().upload_max_bytes  # the default
    assert b.max_sessions == ServiceSettings().token_sessions


def test_a_tokens_caps_default_to_a_share_of_the_servers():
    """One caller cannot take every session or crowd character by default (it could: the
    defaults were the server's own maxima), and an explicit cap still wins."""
    from service.limits import Limiter

    limits = Limiter(ServiceSettings(max_sessions=100, max_characters=1000)).limits_for(None)
    assert (limits.max_sessions, limits.max_characters) == (25, 250)
    default = Limiter(ServiceSettings()).limits_for(None)
    assert default.max_characters < ServiceSettings().max_characters
    assert default.max_sessions < ServiceSettings().max_sessions
    own = Limiter(ServiceSettings(token_max_characters=7, token_max_sessions=3)).limits_for(None)
    assert (own.max_sessions, own.max_characters) == (3, 7)


def test_a_costly_request_takes_its_cost_from_the_bucket_but_never_more_than_it_holds():
    bucket, wait = take(None, 0.0, rate=20.0, burst=40.0, cost=10.0)
    assert (bucket.tokens, wait) == (30.0, 0.0)
    bucket, wait = take(Bucket(5.0, 0.0), 0.0, rate=20.0, burst=40.0, cost=10.0)
    assert wait == pytest.approx(0.25)  # 5 short at 20/s
    _, wait = take(None, 0.0, rate=1.0, burst=2.0, cost=10.0)  # a bucket smaller than the cost: a full one passes
    assert wait == 0.0


@pytest.mark.parametrize(
    "bad",
    [
        {"api_tokens": ["a"], "token_limits": {"typo": {"max_sessions": 1}}},  # a token the server does not have
        {"api_tokens": ["a"], "token_limits": {"a": {"max_sessions": 0}}},
        {"api_tokens": ["a"], "token_limits": {"a": {"sessions": 3}}},  # unknown field
    ],
)
def test_bad_limit_settings_are_refused_at_start(bad):
    with pytest.raises(ValidationError):
        ServiceSettings(**bad)


# ---- on a live server ------------------------------------------------------------------------


def test_rest_requests_over_the_rate_get_429_with_retry_after(server):
    base, _ = server
    codes = [httpx.get(f"{base}/v1/models", headers=auth(RATED)).status_code for _ in range(3)]
    assert codes == [200, 200, 200]  # the burst: 1 request/s x 3 s
    refused = httpx.get(f"{base}/v1/models", headers=auth(RATED))
    assert refused.status_code == 429
    assert refused.json()["code"] == "rate_limited" and "requests/s" in refused.json()["message"]
    assert refused.headers["Retry-After"] == "1"
    assert httpx.get(f"{base}/v1/models", headers=auth(OTHER)).status_code == 200  # another token is not limited
    time.sleep(1.05)
    assert httpx.get(f"{base}/v1/models", headers=auth(RATED)).status_code == 200  # refilled


def test_a_missing_token_gets_401_in_the_error_shape(server):
    base, _ = server
    reply = httpx.get(f"{base}/v1/models", headers=auth("wrong"))
    assert reply.status_code == 401 and reply.json()["code"] == "unauthorized"
    assert reply.headers["WWW-Authenticate"] == "Bearer"


def test_a_token_over_its_session_cap_gets_a_typed_error_and_1013(server):
    base, app = server
    with connect(stream_url(base, CAPPED)) as first, connect(stream_url(base, CAPPED)) as second:
        assert start(first)["type"] == start(second)["type"] == "started"
        with connect(stream_url(base, CAPPED)) as third:
            assert_refused_with_1013(third)
        with connect(stream_url(base, OTHER)) as other:  # the cap is per token
            assert start(other)["type"] == "started"
        first.close()  # a slot comes free once the server has seen the close
        deadline = time.monotonic() + 10
        while app.state.limiter.sessions.get(f"token:{CAPPED}", 0) > 1 and time.monotonic() < deadline:
            time.sleep(0.02)
        with connect(stream_url(base, CAPPED)) as again:
            assert start(again)["type"] == "started"


def test_an_upload_over_the_tokens_size_limit_gets_413(server):
    base, _ = server
    body = json.dumps({"name": "big", "model": "lti", "frames": [[0.0] * 50] * 20})  # ~4 kB of nonsense
    over = httpx.post(f"{base}/v1/styles", content=body, headers={**auth(CAPPED), "Content-Type": "application/json"})
    assert over.status_code == 413 and over.json()["code"] == "too_large"
    assert "2000" in over.json()["message"]
    # the same body is within the default limit of another token: it is read and refused for its content
    other = httpx.post(
        f"{base}/v1/styles",
        content=body,
        headers={**auth(OTHER), "Content-Type": "application/json"},
        timeout=UPLOAD_TIMEOUT_S,
    )
    assert other.status_code == 422 and other.json()["code"] == "bad_request"


def test_anonymous_callers_get_the_default_limits_by_address(models):
    with live_server(models, token_requests_per_s=1, token_burst_s=2, token_max_sessions=1) as (base, _):
        codes = [httpx.get(f"{base}/v1/models").status_code for _ in range(3)]
        assert codes == [200, 200, 429]
        with connect(stream_url(base, "ignored")) as ws:
            assert start(ws)["type"] == "started"
            with connect(stream_url(base, "ignored")) as refused:
                assert_refused_with_1013(refused)
