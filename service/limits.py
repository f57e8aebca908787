"""Who is calling and how much they may use: API tokens and per-token limits.

Every caller is a *principal*: its API token when the server has tokens, otherwise (anonymous
use) its client address. Each principal gets the default limits from the settings, or its own
from `token_limits`:

- concurrent streaming sessions (`max_sessions`): one more is refused with `too_many_sessions`
  and close 1013 (try again later);
- REST requests per second (`requests_per_s`, bursts of `burst_s` seconds' worth): a token
  bucket, so a client that polls steadily is never refused while one that hammers is, with 429
  `rate_limited` and a Retry-After that says when the next request will pass;
- the largest style upload (`upload_max_bytes`): 413 `too_large` above it.

Everything here runs on the event loop, so the counters need no lock.
"""

from __future__ import annotations

import hashlib
import math
import secrets
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

from . import protocol as P
from .api import ApiError
from .settings import ServiceSettings, TokenLimits

CLOSE_TRY_AGAIN_LATER = 1013
CLOSE_FLOODING = 4429  # a connection closed for sending too much (service/transport.py stops reading it)
AUTH_FAILURES_PER_S, AUTH_FAILURES_BURST = 1.0, 10.0  # failed authentications per address
MAX_IDLE_BUCKETS = 10_000  # above this, buckets that have refilled are forgotten (anonymous clients come and go)


@dataclass(frozen=True)
class Limits:
    max_sessions: int
    max_characters: int  # in the caller's crowds together
    requests_per_s: float
    burst: float  # the bucket's size: requests that may come at once
    upload_max_bytes: int
    sessions_per_s: float  # new sessions (resumes included), in bursts of `max_sessions`


@dataclass(frozen=True)
class Principal:
    key: str  # "token:<token>" or "client:<address>"; never sent back to anyone, never stored
    limits: Limits
    admin: bool = False  # an admin token: sees and manages every tenant's styles

    @property
    def id(self) -> str:
        """A stable, one-way name for the caller, safe to keep in snapshots and on disk."""
        return hashlib.sha256(self.key.encode()).hexdigest()[:24]

    @property
    def tenant(self) -> str:
        """Whose uploaded styles and sessions these are: the token's id; "" (one shared tenant)
        when the server runs without tokens, where callers are told apart only by address."""
        return self.id if self.key.startswith("token:") else ""


def _open_burst(limits: Limits) -> float:
    """New sessions that may open at once: all of a caller's sessions, or a second's worth."""
    return float(max(limits.max_sessions, limits.sessions_per_s))


def unauthorized() -> ApiError:
    return ApiError(401, "unauthorized", "missing or invalid API token", {"WWW-Authenticate": "Bearer"})


# ---- token bucket (pure) -------------------------------------------------------------------


@dataclass(frozen=True)
class Bucket:
    tokens: float
    at: float  # clock reading when `tokens` was counted


def level(bucket: Bucket, now: float, rate: float, burst: float) -> float:
    """What a bucket that refills at `rate` per second up to `burst` holds at `now`."""
    return min(burst, bucket.tokens + (now - bucket.at) * rate)


def take(bucket: Bucket | None, now: float, rate: float, burst: float, cost: float = 1.0) -> tuple[Bucket, float]:
    """Take a request costing `cost` (one, or a costly request's worth of them, at most the
    bucket) from a bucket that refills at `rate` per second up to `burst` (a missing bucket is
    full). Returns the bucket after, and 0 when the request may pass or else the seconds until
    it would."""
    cost = min(cost, burst)
    tokens = burst if bucket is None else level(bucket, now, rate, burst)
    if tokens >= cost:
        return Bucket(tokens - cost, now), 0.0
    return Bucket(tokens, now), (cost - tokens) / rate


@dataclass
class MessageRate:
    """One connection's message budget: `rate` per second in bursts of `burst`. Messages over it
    are dropped unread; the first dropped is answered with a typed `rate_limited` error, and a
    second's worth dropped before the client calms down (its bucket full again) closes the
    connection (4429): a client that keeps flooding gets nothing more, and the event loop spends
    almost nothing on it."""

    rate: float
    burst: float
    what: str = "messages"  # what is counted, for the error
    bucket: Bucket | None = None
    excess: int = 0  # messages dropped since the bucket was last full

    def would_admit(self, now: float) -> bool:
        """Whether `admit` would pass a message now (nothing taken): the direct frame path takes
        only what passes, and leaves the rest to the receive loop's `admit`, which answers it."""
        return self.bucket is None or level(self.bucket, now, self.rate, self.burst) >= 1.0

    def admit(self, now: float) -> bool:
        """True: handle the message. False: drop it. Raises the error to send (fatal: close)."""
        self.bucket, wait = take(self.bucket, now, self.rate, self.burst)
        if wait == 0:
            if self.bucket.tokens >= self.burst - 1:  # the bucket was full: the client has calmed down
                self.excess = 0
            return True
        self.excess += 1
        if self.excess == 1:
            raise P.ProtocolError(
                "rate_limited",
                f"more than {self.rate:g} {self.what}/s on this connection (bursts of {self.burst:g}); "
                "messages beyond are dropped, and a second's worth more closes the connection",
            )
        if self.excess >= max(2, self.rate):
            raise P.ProtocolError(
                "rate_limited",
                f"kept sending over {self.rate:g} {self.what}/s after being told",
                fatal=True,
                close_code=CLOSE_FLOODING,
            )
        return False


def given_token(authorization: str | None, query_token: str | None) -> str | None:
    """The token a request carries: `?token=` or `Authorization: Bearer`."""
    if query_token:
        return query_token
    if authorization and authorization.lower().startswith("bearer "):
        return authorization[7:]
    return None


# ---- the limiter -------------------------------------------------------------------------------


@dataclass(frozen=True)
class Meter:
    """A bucket with the rule it refills by, so an idle one can be judged full on its own."""

    bucket: Bucket
    rate: float
    burst: float


class Limiter:
    """Per-principal request buckets and open-session counts for one app."""

    def __init__(self, settings: ServiceSettings, clock: Callable[[], float] = time.monotonic) -> None:
        self.settings, self.clock = settings, clock
        self.buckets: dict[str, Meter] = {}
        self.sessions: Counter[str] = Counter()
        self.cooling: dict[str, float] = {}  # principal key -> clock reading its flood cool-down ends

    def _take(self, key: str, now: float, rate: float, burst: float, cost: float = 1.0) -> float:
        """Take `cost` from the bucket `key` (refilling at `rate` up to `burst`); the wait, 0 if it passes."""
        held = self.buckets.get(key)
        bucket, wait = take(held.bucket if held else None, now, rate, burst, cost)
        self.buckets[key] = Meter(bucket, rate, burst)
        if len(self.buckets) > MAX_IDLE_BUCKETS:
            self._forget_full_buckets(now)
        return wait

    def limits_for(self, token: str | None) -> Limits:
        s = self.settings
        o = s.token_limits.get(token, TokenLimits()) if token is not None else TokenLimits()
        rate = o.requests_per_s or s.token_requests_per_s
        return Limits(
            max_sessions=o.max_sessions or s.token_sessions,
            max_characters=o.max_characters or s.token_characters,
            requests_per_s=rate,
            burst=max(1.0, rate * (o.burst_s or s.token_burst_s)),
            upload_max_bytes=o.upload_max_bytes or s.upload_max_bytes,
            sessions_per_s=s.token_sessions_per_s,
        )

    def identify(self, authorization: str | None, query_token: str | None, client: str | None) -> Principal | None:
        """The caller, or None when the server has tokens and the request carries none of them;
        429 `rate_limited` while the client address has failed too often."""
        if not self.settings.api_tokens:
            return Principal(f"client:{client or 'unknown'}", self.limits_for(None))
        now, failures = self.clock(), f"auth-failures:{client or 'unknown'}"
        held = self.buckets.get(failures)
        left = (
            AUTH_FAILURES_BURST if held is None else level(held.bucket, now, AUTH_FAILURES_PER_S, AUTH_FAILURES_BURST)
        )
        if left < 1.0:
            wait = (1.0 - left) / AUTH_FAILURES_PER_S
            raise ApiError(
                429,
                "rate_limited",
                f"too many failed authentications from this address; retry in {wait:.1f} s",
                {"Retry-After": str(max(1, math.ceil(wait)))},
            )
        given = given_token(authorization, query_token)
        # compare with every token (no early exit), so timing says nothing about which matched
        matches = [t for t in self.settings.api_tokens if given and secrets.compare_digest(given.encode(), t.encode())]
        if not matches:  # counted per address: guessing tokens costs a second per try after the first ten
            self._take(failures, now, AUTH_FAILURES_PER_S, AUTH_FAILURES_BURST)
            return None
        return Principal(f"token:{matches[0]}", self.limits_for(matches[0]), matches[0] in self.settings.admin_tokens)

    def check_request(self, who: Principal, cost: float = 1.0) -> None:
        """Count one REST request (a costly one as `cost` requests: a rig preview); raises 429
        `rate_limited` (with Retry-After) over the rate."""
        wait = self._take(who.key, self.clock(), who.limits.requests_per_s, who.limits.burst, cost)
        if wait > 0:
            raise ApiError(
                429,
                "rate_limited",
                f"more than {who.limits.requests_per_s:g} requests/s (bursts of {who.limits.burst:g}); "
                f"retry in {wait:.2f} s",
                {"Retry-After": str(max(1, math.ceil(wait)))},
            )

    def open_session(self, who: Principal) -> None:
        """Take one of the principal's streaming sessions; raises `too_many_sessions` (close
        1013) when all are taken, or when it opens them faster than `sessions_per_s` (churn
        that would fill the snapshot store). Pair with `session_closed`."""
        if self.sessions[who.key] >= who.limits.max_sessions:
            holder = "this token" if who.key.startswith("token:") else "this client address"
            raise P.ProtocolError(
                "too_many_sessions",
                f"{holder} already holds its maximum of {who.limits.max_sessions} sessions",
                fatal=True,
                close_code=CLOSE_TRY_AGAIN_LATER,
            )
        wait = self._take(f"open:{who.key}", self.clock(), who.limits.sessions_per_s, _open_burst(who.limits))
        if wait > 0:
            raise P.ProtocolError(
                "too_many_sessions",
                f"new sessions faster than {who.limits.sessions_per_s:g}/s; retry in {wait:.2f} s",
                fatal=True,
                close_code=CLOSE_TRY_AGAIN_LATER,
            )
        self.sessions[who.key] += 1

    def flooded(self, who: Principal) -> None:
        """One of the caller's connections was closed for flooding (4429): refuse its new streams
        for `flood_cooldown_s`. Reconnecting at once is what a flood script does, and each new
        connection would cost the server another burst of messages read before the close."""
        if self.settings.flood_cooldown_s > 0:
            now = self.clock()
            if len(self.cooling) >= MAX_IDLE_BUCKETS:
                self.cooling = {k: t for k, t in self.cooling.items() if t > now}
            self.cooling[who.key] = now + self.settings.flood_cooldown_s

    def cooldown_left(self, who: Principal) -> float:
        """Seconds until the caller may open streams again after a flood; 0 if it may now."""
        until = self.cooling.get(who.key)
        if until is None:
            return 0.0
        left = until - self.clock()
        if left <= 0:
            del self.cooling[who.key]
            return 0.0
        return left

    def session_closed(self, who: Principal) -> None:
        self.sessions[who.key] -= 1
        if self.sessions[who.key] <= 0:
            del self.sessions[who.key]

    def _forget_full_buckets(self, now: float) -> None:
        """Drop buckets that have refilled: forgetting a full bucket changes nothing."""
        self.buckets = {k: m for k, m in self.buckets.items() if level(m.bucket, now, m.rate, m.burst) < m.burst}
