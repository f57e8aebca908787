"""The I/O under the SDK's one protocol core: the requests the core yields, and two drivers that
carry them out, one with websockets' and httpx's sync clients, one with their asyncio clients.

The core (`sdk_session`, `sdk_rest`) is written as generators that yield an operation (`Connect`,
`Send`, `Recv`, `Close`, `Sleep`, `Request`) and are sent its result, or have its failure thrown
in as one of three signals (`Disconnected`, `RecvTimeout`, `ConnectFailed`) or a `ServerError`.
Every decision lives in the core once; a driver only decides how to wait, so the sync and asyncio
faces cannot drift apart.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Generator
from contextlib import ExitStack
from dataclasses import dataclass, field
from typing import Any, NamedTuple, TypeVar

import httpx
import websockets
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidURI
from websockets.sync.client import connect as connect_sync

from .sdk_types import ConnectFailed, ServerError
from .sdk_wire import MAX_MESSAGE, Message

T = TypeVar("T")


# ---- operations ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Connect:
    url: str
    timeout: float | None  # the opening handshake
    headers: dict[str, str] = field(default_factory=dict)  # the API token, as Authorization: Bearer


@dataclass(frozen=True)
class Send:
    data: Message


@dataclass(frozen=True)
class Recv:
    timeout: float | None  # 0: only what has arrived already; None: as long as it takes


@dataclass(frozen=True)
class Close:
    pass


@dataclass(frozen=True)
class Sleep:
    seconds: float


@dataclass(frozen=True)
class Request:
    method: str
    path: str
    params: dict[str, Any] | None = None
    json: Any = None
    data: dict[str, str] | None = None
    files: dict[str, Any] | None = None


Op = Connect | Send | Recv | Close | Sleep | Request
Steps = Generator[Op, Any, T]


class HttpReply(NamedTuple):
    status: int
    body: Any  # parsed JSON, None for 204


class Disconnected(Exception):
    """The WebSocket closed (or broke) under a send or receive; `code` is the close code the
    server sent, if any."""

    def __init__(self, code: int | None = None, reason: str = "") -> None:
        super().__init__(f"connection closed ({code}{': ' + reason if reason else ''})")
        self.code, self.reason = code, reason


class RecvTimeout(Exception):
    """Nothing arrived within a `Recv`'s timeout."""


# ---- shared translation -------------------------------------------------------------------------


def _disconnected(exc: Exception) -> Disconnected:
    rcvd = getattr(exc, "rcvd", None)
    return Disconnected(rcvd.code if rcvd else None, rcvd.reason if rcvd else str(exc))


def _http_reply(response: httpx.Response) -> HttpReply:
    """The body of a 2xx answer; anything else as the server's typed error (`{"code", "message"}`),
    or `http_<status>` when the body is not one (a proxy's error page)."""
    if response.status_code < 400:
        return HttpReply(response.status_code, response.json() if response.content else None)
    try:
        body = response.json()
        code, message = str(body["code"]), str(body["message"])
    except (ValueError, KeyError, TypeError):
        code, message = f"http_{response.status_code}", response.text[:200]
    retry = response.headers.get("retry-after")
    raise ServerError(
        code,
        message,
        status=response.status_code,
        retry_after=float(retry) if retry and retry.replace(".", "", 1).isdigit() else None,
    )


def _request_args(op: Request) -> dict[str, Any]:
    return {"params": op.params, "json": op.json, "data": op.data, "files": op.files}


# ---- sync ---------------------------------------------------------------------------------------


class SyncIO:
    """Carries out operations with websockets' sync client (one connection at a time, `ws`) and
    an httpx.Client."""

    def __init__(self, http: httpx.Client | None = None) -> None:
        self.http = http
        self.ws: Any = None  # websockets.sync.client.ClientConnection while connected
        self._connection = ExitStack()  # websockets wants its sync connection used as a context manager

    def perform(self, op: Op) -> Any:
        if isinstance(op, Recv):
            try:
                return self.ws.recv(timeout=op.timeout)
            except TimeoutError:
                raise RecvTimeout() from None
            except ConnectionClosed as exc:
                raise _disconnected(exc) from None
        if isinstance(op, Send):
            try:
                return self.ws.send(op.data)
            except (ConnectionClosed, OSError) as exc:
                raise _disconnected(exc) from None
        if isinstance(op, Connect):
            self._connection = ExitStack()
            try:
                self.ws = self._connection.enter_context(
                    connect_sync(
                        op.url,
                        additional_headers=op.headers,
                        open_timeout=op.timeout,
                        max_size=MAX_MESSAGE,
                        compression=None,
                    )
                )
            except (OSError, InvalidHandshake, InvalidURI) as exc:
                raise ConnectFailed(f"cannot open a session at {op.url}: {exc}") from exc
            return None
        if isinstance(op, Close):
            try:
                self._connection.close()
            except Exception:  # noqa: BLE001 - closing an already broken socket
                pass
            return None
        if isinstance(op, Sleep):
            time.sleep(op.seconds)
            return None
        assert self.http is not None, "REST request without an HTTP client"
        return _http_reply(self.http.request(op.method, op.path, **_request_args(op)))


def run_sync(steps: Steps[T], io: SyncIO) -> T:
    """Drive a core generator to its end with `io`; its return value is the result."""
    reply: Any = None
    error: Exception | None = None
    while True:
        try:
            op = steps.throw(error) if error is not None else steps.send(reply)
        except StopIteration as done:
            return done.value
        try:
            reply, error = io.perform(op), None
        except Exception as exc:  # noqa: BLE001 - handed to the core, which decides
            reply, error = None, exc


# ---- asyncio ------------------------------------------------------------------------------------


class AsyncIO:
    """The same operations with websockets' asyncio client and an httpx.AsyncClient."""

    def __init__(self, http: httpx.AsyncClient | None = None) -> None:
        self.http = http
        self.ws: Any = None  # websockets.asyncio.client.ClientConnection while connected

    async def perform(self, op: Op) -> Any:
        if isinstance(op, Recv):
            try:
                async with asyncio.timeout(op.timeout):  # recv() is cancellation-safe: nothing is lost
                    return await self.ws.recv()
            except TimeoutError:
                raise RecvTimeout() from None
            except ConnectionClosed as exc:
                raise _disconnected(exc) from None
        if isinstance(op, Send):
            try:
                return await self.ws.send(op.data)
            except (ConnectionClosed, OSError) as exc:
                raise _disconnected(exc) from None
        if isinstance(op, Connect):
            try:
                self.ws = await websockets.connect(
                    op.url,
                    additional_headers=op.headers,
                    open_timeout=op.timeout,
                    max_size=MAX_MESSAGE,
                    compression=None,
                )
            except (OSError, InvalidHandshake, InvalidURI) as exc:
                raise ConnectFailed(f"cannot open a session at {op.url}: {exc}") from exc
            return None
        if isinstance(op, Close):
            if self.ws is not None:
                try:
                    await self.ws.close()
                except Exception:  # noqa: BLE001
                    pass
            return None
        if isinstance(op, Sleep):
            await asyncio.sleep(op.seconds)
            return None
        assert self.http is not None, "REST request without an HTTP client"
        return _http_reply(await self.http.request(op.method, op.path, **_request_args(op)))


async def run_async(steps: Steps[T], io: AsyncIO) -> T:
    """`run_sync` for asyncio."""
    reply: Any = None
    error: Exception | None = None
    while True:
        try:
            op = steps.throw(error) if error is not None else steps.send(reply)
        except StopIteration as done:
            return done.value
        try:
            reply, error = await io.perform(op), None
        except Exception as exc:  # noqa: BLE001
            reply, error = None, exc
