"""A streaming session's protocol logic, once, for the sync and asyncio faces (see `sdk_io`).

Every message the caller sends becomes an `Entry` in `pending`, in send order. An entry is first
unsent, then sent, then resolved by its reply (a frame, a control acknowledgement, or an error),
and leaves `pending` from the front once resolved, so replies reach the caller in send order:

- a *call* (`stylise`, `control`, `set_style`, `reset`) waits for its own entry's reply;
- a *pipelined* send (`send`, `send_control`) does not wait: its reply is queued in `ready` for
  `receive()` / `poll()`, and up to `window` messages are in flight at once, so a game loop sends
  frame t without waiting for t-1's reply (keep the window at or below the server's session queue,
  `STYLESTREAM_SESSION_QUEUE`, 8 by default, or the server drops the oldest frames).

When the connection goes, the session reconnects with its resume token, backing off
exponentially until `reconnect_timeout`. The server's `started.last_seq` says how far the
restored state has seen; the replay buffer's messages after it are sent again one at a time
(a burst would overrun the server's queue), and replies the caller already has are discarded, so
outputs equal an uninterrupted run's. A server that no longer knows the token (restarted without
a shared store, or the snapshot expired) gets a fresh session with the same settings and the
current style, and the unanswered messages are sent to it. Either way the caller is told
(`on_reconnect`, `last_reconnect`).
"""

from __future__ import annotations

import json
import logging
import random
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from .sdk_io import Close, Connect, Disconnected, Recv, RecvTimeout, Send, Sleep, Steps
from .sdk_types import (
    ConnectFailed,
    ConnectionLost,
    FrameDropped,
    NothingInFlight,
    Reconnect,
    ReplyTimeout,
    ResumeError,
    ServerError,
    StyledFrame,
    StylestreamError,
)
from .sdk_wire import (
    END,
    RESET,
    Message,
    ReplayBuffer,
    StartSettings,
    ack_for,
    control_message,
    json_frame,
    pack,
    saved_reply,
    server_error,
    start_message,
    style_message,
    unpack,
)

log = logging.getLogger("clients.sdk")

RETRY_CODES = {"session_in_use", "draining", "store_unavailable", "too_many_sessions"}  # a later attempt may succeed
BACKOFF_FIRST_S, BACKOFF_MAX_S = 0.05, 2.0  # reconnect delays double from the first to the cap (with jitter)
CLOSE_UNAUTHORIZED = 4401
CALL, QUEUE, DISCARD = "call", "queue", "discard"  # who takes an entry's reply

DROPPED = object()  # the server dropped the frame (backpressure)
LOST = object()  # the restored state holds the frame, but its reply went with the old connection


@dataclass(eq=False)
class Entry:
    """One message the session sent or will send, until its reply is taken."""

    seq: int | None  # frames and control ticks: their sequence number; control messages: None
    message: Message
    mode: str  # CALL, QUEUE or DISCARD (a replayed message whose reply the caller already has)
    ack: str | None = None  # a control message's reply type ('style_set', 'reset_done')
    style: tuple[str | None, dict[str, float] | None, float] | None = None  # a set_style's target
    sent: bool = False
    replayed: bool = False  # sent again after a resume: one at a time
    outcome: Any = None  # StyledFrame | dict | ServerError | DROPPED | LOST
    notices: list[ServerError] = field(default_factory=list)


class SessionCore:
    """The state and protocol of one streaming session; its methods are generators driven by
    `sdk_io.run_sync` / `run_async`."""

    def __init__(
        self,
        url: str,
        settings: StartSettings,
        *,
        headers: dict[str, str] | None = None,
        timeout: float | None,
        reconnect_timeout: float | None,
        max_in_flight: int,
        on_reconnect: Callable[[Reconnect], None] | None,
    ) -> None:
        if max_in_flight < 1:
            raise ValueError("max_in_flight must be at least 1")
        self.url, self.settings, self.headers = url, settings, headers or {}
        self.timeout, self.reconnect_timeout, self.window = timeout, reconnect_timeout, max_in_flight
        self.on_reconnect = on_reconnect
        self.seq = 0
        self.replay = ReplayBuffer()
        self.pending: deque[Entry] = deque()
        self.ready: deque[StyledFrame | ServerError] = deque()
        self.info: dict[str, Any] = {}
        self.joints: list[str] = []
        self.resume_token: str | None = None
        self.reconnects = 0  # resumes after a lost connection
        self.new_sessions = 0  # fresh sessions after a lost one the server no longer knew
        self.last_reconnect: Reconnect | None = None
        self.notices: list[ServerError] = []  # errors that answer nothing this session sent
        self.connected = self.closed = False

    # ---- the caller's operations ---------------------------------------------------------------
    def open(self) -> Steps[dict[str, Any]]:
        """Open the session; a refusal is raised at once (no retries: a wrong address or setting
        should fail fast)."""
        return (yield from self._start(None))

    def stylise(self, root: np.ndarray, rotations: np.ndarray) -> Steps[StyledFrame]:
        seq = self._next_seq()
        return (yield from self._call(Entry(seq, pack(seq, root, rotations), CALL)))

    def control(self, velocity: tuple[float, float], facing: float, gait: str) -> Steps[StyledFrame]:
        seq = self._next_seq()
        return (yield from self._call(Entry(seq, control_message(seq, velocity, facing, gait), CALL)))

    def set_style(
        self, style: str | None, mix: dict[str, float] | None, intensity: float, transition_frames: int
    ) -> Steps[dict[str, Any]]:
        message = style_message(style, mix, intensity, transition_frames)
        return (yield from self._call(Entry(None, message, CALL, "style_set", (style, mix, intensity))))

    def reset(self) -> Steps[dict[str, Any]]:
        return (yield from self._call(Entry(None, RESET, CALL, "reset_done")))

    def send(self, root: np.ndarray, rotations: np.ndarray) -> Steps[int]:
        """Pipelined: send a frame without waiting for its reply (only for room in the window)."""
        seq = self._next_seq()
        return (yield from self._queue(Entry(seq, pack(seq, root, rotations), QUEUE)))

    def send_control(self, velocity: tuple[float, float], facing: float, gait: str) -> Steps[int]:
        seq = self._next_seq()
        return (yield from self._queue(Entry(seq, control_message(seq, velocity, facing, gait), QUEUE)))

    def receive(self, timeout: float | None) -> Steps[StyledFrame]:
        """The next pipelined reply, in send order."""
        yield from self._pump(lambda: bool(self.ready) or not self._queued(), _deadline(timeout))
        if not self.ready:
            raise NothingInFlight("no pipelined frame is waiting for its reply")
        return self._take_ready()

    def poll(self) -> Steps[list[StyledFrame]]:
        """The pipelined replies that have arrived, without waiting; an error answering a frame is
        raised when it is next in line."""
        yield from self._pump(lambda: False, _deadline(0.0), drain=True)
        out: list[StyledFrame] = []
        while self.ready and isinstance(self.ready[0], StyledFrame):
            out.append(self._take_ready())
        if not out and self.ready:
            self._take_ready()  # raises the error
        return out

    def in_flight(self) -> int:
        """Pipelined frames sent or waiting to be sent whose replies the caller has not taken."""
        return self._queued() + len(self.ready)

    def close(self) -> Steps[None]:
        """End the session (`end`, then the server's `ended`, briefly) and close the socket.
        Replies still in flight are discarded; an ended session cannot be resumed."""
        if self.closed:
            return
        self.closed = True
        if self.connected:
            try:
                yield Send(END)
                deadline = _deadline(min(self.timeout or 5.0, 5.0))
                while True:
                    data = yield Recv(_remaining(deadline))
                    if isinstance(data, str) and json.loads(data).get("type") == "ended":
                        break
            except (Disconnected, RecvTimeout):
                pass
        self.connected = False
        yield Close()

    # ---- sending and receiving -------------------------------------------------------------------
    def _next_seq(self) -> int:
        if self.closed:
            raise StylestreamError("the session is closed")
        seq, self.seq = self.seq, self.seq + 1
        return seq

    def _submit(self, entry: Entry) -> Entry:
        self.replay.add(entry.seq, entry.message)
        self.pending.append(entry)
        return entry

    def _call(self, entry: Entry) -> Steps[Any]:
        if self.closed:
            raise StylestreamError("the session is closed")
        self._submit(entry)
        try:
            yield from self._pump(lambda: entry.outcome is not None, _deadline(self.timeout))
        except ReplyTimeout:
            entry.mode = DISCARD  # its reply, if it comes, is nobody's
            raise
        return _result(entry)

    def _queue(self, entry: Entry) -> Steps[int]:
        self._submit(entry)
        yield from self._pump(lambda: entry.sent or entry.outcome is not None, _deadline(self.timeout))
        assert entry.seq is not None
        return entry.seq

    def _queued(self) -> int:
        return sum(1 for e in self.pending if e.mode == QUEUE and e.outcome is None)

    def _pump(self, done: Callable[[], bool], deadline: float | None, drain: bool = False) -> Steps[None]:
        """Send what the window allows and read replies until `done()`, reconnecting when the
        connection goes. With `drain` (poll), only until nothing more has arrived, and a lost
        connection is left to the next call that waits, so a game loop's poll never blocks."""
        while not done():
            entry = self._next_to_send()
            if entry is not None:
                entry.sent = True
                try:
                    yield Send(entry.message)
                except Disconnected as gone:
                    entry.sent = False
                    if drain:
                        return
                    yield from self._recover(gone)
                continue
            try:
                data = yield Recv(_remaining(deadline))
            except RecvTimeout:
                if drain:
                    return
                raise ReplyTimeout(
                    f"no reply within {self.timeout:g} s" if self.timeout is not None else "no reply"
                ) from None
            except Disconnected as gone:
                if drain:
                    return
                yield from self._recover(gone)
                continue
            self._on_message(data)

    def _next_to_send(self) -> Entry | None:
        """The first unsent entry if the window has room: `window` messages in flight, one while
        a replay is under way."""
        unsent = next((e for e in self.pending if not e.sent), None)
        if unsent is None:
            return None
        flying = [e for e in self.pending if e.sent and e.outcome is None]
        limit = 1 if unsent.replayed or any(e.replayed for e in flying) else self.window
        return unsent if len(flying) < limit else None

    def _on_message(self, data: Message) -> None:
        if isinstance(data, bytes):
            self._on_frame(unpack(data, len(self.joints)))
        else:
            message = json.loads(data)
            kind = message.get("type")
            if kind == "frame":
                self._on_frame(json_frame(message))
            elif kind == "snapshot":
                self.replay.acknowledged(message["last_seq"])
            elif kind in ("style_set", "reset_done"):
                entry = next((e for e in self.pending if e.sent and e.outcome is None and e.ack == kind), None)
                if entry is not None:
                    entry.outcome = message
                    if entry.style is not None:  # a fresh session after a lost one starts in this style
                        self.settings = self.settings.restyled(*entry.style)
            elif kind == "error":
                self._on_error(server_error(message))
        self._settle()

    def _on_frame(self, frame: StyledFrame) -> None:
        """A frame's reply; frames sent before it and still unanswered were dropped (backpressure:
        the server drops the oldest queued frames and answers in order)."""
        frames = [e for e in self.pending if e.sent and e.ack is None]
        match = next((i for i, e in enumerate(frames) if e.seq == frame.seq), None)
        if match is None:
            return  # a reply nobody waits for (to a message sent outside the SDK)
        for e in frames[:match]:
            if e.outcome is None:
                e.outcome = DROPPED
        entry = frames[match]
        if entry.outcome is None:
            entry.outcome = replace(frame, notices=tuple(entry.notices)) if entry.notices else frame

    def _on_error(self, err: ServerError) -> None:
        """An error answers the frame it names, or else the oldest unanswered control message;
        `style_deleted` is a notice that comes before its frame's reply."""
        unanswered = [e for e in self.pending if e.sent and e.outcome is None]
        if err.code == "style_deleted":
            target = next((e for e in unanswered if e.seq == err.seq), None)
        elif err.seq is not None:
            target = next((e for e in unanswered if e.seq == err.seq and e.ack is None), None)
        else:
            target = next((e for e in unanswered if e.ack is not None), None)
        if target is None:
            self.notices.append(err)
        elif err.code == "style_deleted":
            target.notices.append(err)
        else:
            target.outcome = err

    def _settle(self) -> None:
        """Answered entries leave from the front, in send order; pipelined replies go to `ready`."""
        while self.pending and self.pending[0].outcome is not None:
            entry = self.pending.popleft()
            if entry.mode == QUEUE and entry.outcome is not DROPPED and entry.outcome is not LOST:
                self.ready.append(entry.outcome)

    def _take_ready(self) -> StyledFrame:
        item = self.ready.popleft()
        if isinstance(item, ServerError):
            raise item
        return item

    # ---- connecting and reconnecting ----------------------------------------------------------
    def _start(self, token: str | None) -> Steps[dict[str, Any]]:
        """Connect and send `start` (resuming with `token`); raises `ServerError` for a typed
        refusal and `ConnectFailed` for anything else."""
        yield Connect(self.url, self.timeout, self.headers)
        try:
            yield Send(start_message(self.settings, token))
            data = yield Recv(self.timeout)
        except RecvTimeout:
            yield Close()
            raise ConnectFailed(f"no answer to 'start' from {self.url} within {self.timeout:g} s") from None
        except Disconnected as gone:
            yield Close()
            if gone.code == CLOSE_UNAUTHORIZED:
                raise ServerError("unauthorized", gone.reason or "a valid API token is required") from None
            raise ConnectFailed(f"the connection to {self.url} closed before 'started': {gone}") from None
        message = json.loads(data) if isinstance(data, str) else {}
        if message.get("type") != "started":
            yield Close()
            if message.get("type") == "error":
                raise server_error(message)
            raise ConnectFailed(f"unexpected answer to 'start': {str(data)[:200]}")
        self.info, self.joints, self.resume_token = message, message["joints"], message["resume_token"]
        self.connected = True
        return message

    def _recover(self, gone: Disconnected) -> Steps[None]:
        """The connection went: come back, resumed or fresh, and queue what must be sent again."""
        self.connected = False
        yield Close()
        began = time.monotonic()
        started, attempts, resumed = yield from self._reconnect(gone)
        if resumed:
            replayed, lost = self._plan_resume(started)
            self.reconnects += 1
        else:
            replayed, lost = self._plan_fresh(), ()
            self.new_sessions += 1
        event = Reconnect(
            "resumed" if resumed else "new_session",
            attempts,
            time.monotonic() - began,
            started["session_id"],
            started.get("last_seq") if resumed else None,
            replayed,
            lost,
            str(gone),
        )
        self.last_reconnect = event
        log.info(
            "session %s %s after %d attempt(s), %.2f s: %d message(s) replayed, %d reply(ies) lost",
            event.session_id,
            event.kind.replace("_", " "),
            attempts,
            event.seconds,
            replayed,
            len(lost),
        )
        self._settle()
        if self.on_reconnect is not None:
            self.on_reconnect(event)

    def _reconnect(self, gone: Disconnected) -> Steps[tuple[dict[str, Any], int, bool]]:
        """Attempt after attempt until `reconnect_timeout`: resume with the token; if the server no
        longer knows it, at once a fresh session. Returns the `started` reply, the attempts made
        and whether it is a resume."""
        deadline = _deadline(self.reconnect_timeout)
        token, delay, attempts = self.resume_token, BACKOFF_FIRST_S, 0
        last: Exception = ConnectFailed(str(gone))
        while True:
            attempts += 1
            try:
                started = yield from self._start(token)
                return started, attempts, token is not None
            except ServerError as err:
                if err.code == "unknown_resume_token" and token is not None:
                    token = None  # the server restarted without a shared store, or the snapshot expired
                    continue
                if err.code not in RETRY_CODES:
                    raise
                last = err
            except ConnectFailed as err:
                last = err
            left = _remaining(deadline)
            if left is not None and left <= 0:
                raise ConnectionLost(
                    f"lost the connection to {self.url} ({gone}) and could not get back within "
                    f"{self.reconnect_timeout:g} s ({attempts} attempts): {last}"
                ) from last
            pause = delay * random.uniform(0.5, 1.0)  # jitter: clients of a restarted server do not return in step
            pause = pause if left is None else min(pause, left)
            log.info("reconnect attempt %d to %s failed (%s); next in %.2f s", attempts, self.url, last, pause)
            yield Sleep(pause)
            delay = min(delay * 2, BACKOFF_MAX_S)

    def _plan_resume(self, started: dict[str, Any]) -> tuple[int, tuple[int, ...]]:
        """Queue the replay buffer's messages after the restored `last_seq` to be sent again, one
        at a time; messages the snapshot already holds get their replies from it where it has
        them (`last_frame`), else are reported lost. Returns (messages replayed, lost frames)."""
        last = started["last_seq"]
        missing = self.replay.after(last)  # ResumeError if the buffer and the snapshot do not meet
        again = {id(m) for _, m in missing}
        lost: list[int] = []
        for e in self.pending:
            if e.outcome is not None or id(e.message) in again:
                continue
            if e.ack is not None:  # the snapshot holds this control message; its acknowledgement went
                e.outcome = {"type": e.ack, "restored": True}
                continue
            saved = saved_reply(started, e.seq)
            e.outcome = saved if saved is not None else LOST
            if saved is None and e.seq is not None:
                lost.append(e.seq)
        known = {id(e.message): e for e in self.pending}
        answered = [Entry(seq, m, DISCARD, ack_for(seq, m)) for seq, m in missing if id(m) not in known]
        for e in answered:  # already answered, so older than every pending entry
            e.replayed = True
        for e in self.pending:
            if id(e.message) in again:
                e.sent, e.replayed = False, True
        self.pending.extendleft(reversed(answered))
        return len(missing), tuple(lost)

    def _plan_fresh(self) -> int:
        """A fresh session: the unanswered messages go to it as new ones."""
        self.replay = ReplayBuffer(self.replay.limit)
        resend = 0
        for e in self.pending:
            if e.outcome is None:
                e.sent, e.replayed = False, False
                self.replay.add(e.seq, e.message)
                resend += 1
        return resend


def _result(entry: Entry) -> Any:
    outcome = entry.outcome
    if isinstance(outcome, ServerError):
        raise outcome
    if outcome is DROPPED:
        raise FrameDropped(f"the server dropped frame {entry.seq} (its session queue was full)")
    if outcome is LOST:
        raise ResumeError("the server saved the last message but its reply was lost")
    return outcome


def _deadline(timeout: float | None) -> float | None:
    return None if timeout is None else time.monotonic() + timeout


def _remaining(deadline: float | None) -> float | None:
    return None if deadline is None else max(0.0, deadline - time.monotonic())
