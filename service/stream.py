"""`WS /v1/stream`: one WebSocket connection = one session (or one crowd: `service.crowd_stream`).

Two tasks per connection: the receiver parses and validates messages and queues work on the
session (bad frames get a typed error and are skipped; protocol violations close the socket),
and the processor takes queued work in order, runs frames through the model's batcher and sends
each result back with the frame's sequence number. One send lock keeps replies whole.

The direct path: while a session has nothing queued or in hand, its next binary frame is taken
straight from the WebSocket protocol (`transport.DIRECT_FRAMES`), stepped in the batch, and
answered from the step's callback, with no task of the connection woken: the same work as the
processor's, in the same order, at a fraction of the event loop's cost per frame. Whatever it
cannot finish at once (a bad or rate-limited frame, a deleted style, a peer not reading) it
leaves to the two tasks above.

If the client goes away, frames still queued are left unprocessed: its resume replays them, so
the saved state never runs ahead of the replies the client has. A drain (SIGTERM) stops the
processor after its current frame, and the runtime closes the socket with 1012 once the
session's snapshot is stored.
"""

from __future__ import annotations

import asyncio
import functools
import json
import logging
import time
from collections import deque
from collections.abc import Coroutine
from typing import Any, TypeVar

import numpy as np
from starlette.websockets import WebSocket, WebSocketDisconnect, WebSocketState

from models.motion.novelty_stage import faded
from models.motion.rate import output_delay_s

from . import pipelines
from . import protocol as P
from .deps import get_limiter
from .limits import CLOSE_FLOODING, MessageRate, Principal
from .logs import session_log
from .metrics import ModelMetrics
from .pacing import LoopShare
from .runtime import Runtime
from .sessions import ControlItem, FrameItem, Session, Snapshot
from .skeletons import SkeletonAdapter
from .transport import DIRECT_FRAMES, GuardedWebSocket

log = logging.getLogger(__name__)

CLOSE_NORMAL, CLOSE_INTERNAL, CLOSE_RESTART = 1000, 1011, 1012
CLOSE_UNAUTHORIZED, CLOSE_IDLE = 4401, 4408
T = TypeVar("T")
YIELD_EVERY = 8  # messages handled back to back before the receiver lets other connections run
# What reading a message costs at most against the connection's `LoopShare`: one already queued is
# read in ~30-60 us; a longer read was mostly waiting for the client, which costs the loop nothing
READ_CHARGE_S = 0.0002


class Socket:
    """One WebSocket connection: replies sent whole under one lock, messages received under the
    idle timeout and size limit, the per-connection message rates, and the receive loop feeding
    a processor task. What the messages mean is the subclass's: `Connection` (one session) or
    `service.crowd_stream.CrowdConnection` (many characters, protocol v1.1); `serve` picks it
    from the first message."""

    def __init__(self, ws: WebSocket, runtime: Runtime, who: Principal) -> None:
        self.ws, self.rt, self.who = ws, runtime, who
        self.settings, self.metrics = runtime.settings, runtime.metrics
        self.send_lock = asyncio.Lock()
        self.wakeup = asyncio.Event()
        self.closing = False  # no more input: process what is queued, then stop
        self.stopping = False  # stop after the current item (client gone, or draining)
        self.processor: asyncio.Task | None = None
        self.heard = time.monotonic()  # when the client's last message came (the idle timeout)
        self.worked = self.heard  # when the processor last finished its work in hand (the idle timeout)
        self.receiving = False  # the receiver waits for a message, with none in hand
        self.parked = False  # the processor waits for work, with none in hand
        self.direct_busy = False  # a frame taken by the direct path is not yet answered (`Connection`)
        self.rate = MessageRate(self.settings.max_messages_per_s, self.settings.max_messages_per_s)
        self.control_rate = MessageRate(
            self.settings.max_controls_per_s, self.settings.max_controls_per_s, "style and reset messages"
        )
        self.share = LoopShare(self.settings.connection_loop_share)  # a flood gets its share of the loop
        self.log: logging.Logger | logging.LoggerAdapter = log  # once open: its id and model on every line
        self._failing: asyncio.Task | None = None  # ending the connection after its processor failed

    # ---- what a subclass does with the messages -------------------------------------
    async def open(self, first: P.Start | P.CrowdStart) -> bool:
        """Act on the first message; False if the connection is to close (refused, and told)."""
        raise NotImplementedError

    def on_binary(self, data: bytes) -> None:
        raise NotImplementedError

    async def on_text_or_refresh(self, data: str) -> bool:
        """A text message after the first; False once it ended the connection."""
        raise NotImplementedError

    async def process(self) -> None:
        """The processor task: queued work in order, until `stopping` (or `closing` and done)."""
        raise NotImplementedError

    def finish(self) -> None:
        """The connection is over and its processor stopped: release what it held."""

    async def stop_processing(self) -> None:
        """Drain, step 1: finish the current frame, process nothing more, queue the snapshot."""
        raise NotImplementedError

    async def close_for_restart(self) -> None:
        """Drain, step 2 (the snapshot is stored): close with 1012."""
        raise NotImplementedError

    # ---- sending ------------------------------------------------------------------
    def _sendable(self) -> bool:
        """Neither side has closed (a snapshot acknowledgement may come after our close)."""
        return (
            self.ws.client_state == WebSocketState.CONNECTED and self.ws.application_state == WebSocketState.CONNECTED
        )

    async def send_json(self, payload: dict) -> None:
        async with self.send_lock:
            if self._sendable():
                await self.ws.send_text(json.dumps(payload))

    async def send_bytes(self, data: bytes) -> None:
        async with self.send_lock:
            if self._sendable():
                await self.ws.send_bytes(data)

    async def send_error(self, err: P.ProtocolError) -> None:
        self.metrics.errors.labels(err.code).inc()
        await self.send_json(P.error_message(err.code, err.message, err.seq, err.character))

    async def close(self, code: int, reason: str = "") -> None:
        self.closing = True
        self.wakeup.set()
        async with self.send_lock:
            if self._sendable():
                await self.ws.close(code, P.close_reason(reason))

    # ---- receiving ----------------------------------------------------------------
    @property
    def working(self) -> bool:
        """The processor has an item of the client's in hand (a join's rig builds can take
        seconds on a busy server): the client waits for us, it is not idle."""
        return self.processor is not None and not self.parked and not self.processor.done()

    async def receive(self) -> str | bytes | None:
        idle = self.settings.idle_timeout_s
        while True:
            self.receiving = True
            try:
                # idle from the client's last message or the end of the work it asked for, if later
                left = idle if self.working else max(self.heard, self.worked) + idle - time.monotonic()
                async with asyncio.timeout(left):  # a timer, not wait_for's task
                    message = await self.ws.receive()
                break
            except TimeoutError:
                if self.working or time.monotonic() - max(self.heard, self.worked) < idle:
                    continue  # still at its work, or frames came by the direct path meanwhile
                await self.send_error(P.ProtocolError("idle_timeout", f"no message for {idle:g} s"))
                await self.close(CLOSE_IDLE, "idle timeout")
                return None
            finally:
                self.receiving = False
        self.heard = time.monotonic()
        if message["type"] == "websocket.disconnect":
            return None
        data = message.get("text") if message.get("text") is not None else message.get("bytes")
        if data is not None and len(data) > self.settings.max_message_bytes:
            raise P.ProtocolError(
                "message_too_large",
                f"message of {len(data)} bytes exceeds the limit of {self.settings.max_message_bytes}",
            )
        return data

    async def first_message(self) -> P.Start | P.CrowdStart | None:
        """The opening message, parsed; None when the client left first or sent something else
        (it was told, with a fatal error)."""
        try:
            data = await self.receive()
            if data is None:
                return None
            if isinstance(data, bytes):
                raise P.ProtocolError("expected_start", "the first message must be a JSON 'start' message", fatal=True)
            message = P.parse_text(data)
            if not isinstance(message, P.Start | P.CrowdStart):
                raise P.ProtocolError(
                    "expected_start", f"the first message must be 'start', got '{message.type}'", fatal=True
                )
            return message
        except P.ProtocolError as err:
            await self.refuse(err)
            return None

    async def next_work(self, pending: deque[T]) -> T | None:
        """The processor's next queued item; None once `stopping`, or `closing` with nothing left.
        A frame the direct path has in hand is answered first, and before it returns None."""
        while not self.stopping:
            if not self.direct_busy:
                if pending:
                    return pending.popleft()
                if self.closing:
                    return None
            await self._park()
        while self.direct_busy:
            await self._park()
        return None

    async def _park(self) -> None:
        self.parked = True
        self.worked = time.monotonic()
        self.wakeup.clear()
        try:
            await self.wakeup.wait()
        finally:
            self.parked = False

    async def refuse(self, err: P.ProtocolError) -> None:
        """A fatal error: told, then the socket closed with the error's code."""
        err.fatal = True
        await self.send_error(err)
        await self.close(err.close_code, err.message)

    def _processor_done(self, task: asyncio.Task) -> None:
        """The processor ended. If by an exception (a bug, or a model or rig failure nothing
        caught), the connection ends with it: a log line with the traceback, a fatal typed
        `internal` error and close 1011, so the client reconnects and resumes instead of waiting
        on a connection nobody serves (it hung for ever, with nothing logged)."""
        if task.cancelled() or task.exception() is None:
            return
        self.log.error("processor failed; closing the connection", exc_info=task.exception())
        self.stopping = True
        failing = asyncio.get_running_loop().create_task(self._end_failed())
        self._failing = failing  # held until it has run (the loop keeps only a weak reference)

    async def _end_failed(self) -> None:
        err = P.ProtocolError(
            "internal",
            "the server failed on this connection; connect again (resume with your resume token)",
            fatal=True,
            close_code=CLOSE_INTERNAL,
        )
        try:
            await self.refuse(err)
        except Exception:  # noqa: BLE001 - the client left meanwhile: its disconnect ends the receive loop
            self.log.debug("failure not sent", exc_info=True)

    async def run(self, first: P.Start | P.CrowdStart) -> None:
        try:
            if not await self.open(first):
                return
            self.parked = True  # the processor has nothing in hand; its first act is to wait for work
            self.processor = asyncio.create_task(self.process())
            self.processor.add_done_callback(self._processor_done)
            handled = 0
            while not self.closing:
                asked, began = time.perf_counter(), 0.0  # began: when the message was in hand
                try:
                    data = await self.receive()
                    began = time.perf_counter()
                    if data is None:
                        self.stopping = True
                        break
                    handled += 1
                    if handled % YIELD_EVERY == 0:  # what one read queued must not hold the loop from everyone else
                        await asyncio.sleep(0)
                        began = time.perf_counter()
                    if not self.rate.admit(time.monotonic()):
                        continue
                    if isinstance(data, bytes):
                        self.on_binary(data)
                    elif not await self.on_text_or_refresh(data):
                        break
                except P.ProtocolError as err:
                    began = began or time.perf_counter()  # refused by the read itself, after its wait
                    await self.send_error(err)
                    if err.fatal:
                        if err.close_code == CLOSE_FLOODING:  # its reconnects are refused for a while
                            get_limiter(self.ws).flooded(self.who)
                        await self.close(err.close_code, err.message)
                        break
                # a refused message (its error told) costs as one taken: a flood of bad frames too
                await self.share.spend(min(began - asked, READ_CHARGE_S) + time.perf_counter() - began)
        except WebSocketDisconnect:
            self.stopping = True
        finally:
            self.closing = True
            self.wakeup.set()
            if self.processor is not None:
                await asyncio.gather(self.processor, return_exceptions=True)
            self.finish()


async def serve(ws: WebSocket, runtime: Runtime, who: Principal) -> None:
    """Run a connection to its end: a session (`start`) or a crowd (`crowd`, protocol v1.1)."""
    from .crowd_stream import CrowdConnection

    opening = Connection(ws, runtime, who)
    first = await opening.first_message()
    if first is None:
        return
    connection: Socket = CrowdConnection(ws, runtime, who) if isinstance(first, P.CrowdStart) else opening
    await connection.run(first)


def delay_ms(model_fps: float, fps: float) -> float:
    """The fixed delay of a reply behind its frame at this rate (`models.motion.rate`), in ms."""
    return round(output_delay_s(model_fps, fps) * 1000.0, 3)


def style_deleted(gone: list[str], seq: int) -> P.ProtocolError:
    return P.ProtocolError(
        "style_deleted",
        f"style(s) {', '.join(gone)} were deleted; their share of the mix now passes the input through",
        seq,
    )


def step_failed(seq: int) -> P.ProtocolError:
    return P.ProtocolError("internal", "model step failed", seq)


class Connection(Socket):
    """One session on the connection (protocol v1)."""

    def __init__(self, ws: WebSocket, runtime: Runtime, who: Principal) -> None:
        super().__init__(ws, runtime, who)
        self._session: Session | None = None
        self._adapter: SkeletonAdapter | None = None
        self.acks = False  # the client asked for snapshot acknowledgements
        self._send_tasks: set[asyncio.Task] = set()
        self.direct: GuardedWebSocket | None = None  # the protocol's direct frame path, once offered

    @property
    def session(self) -> Session:
        """The session `open` opened; everything after the start message works on it."""
        if self._session is None:
            raise RuntimeError("no session opened on this connection")
        return self._session

    @property
    def adapter(self) -> SkeletonAdapter:
        """The client's rig <-> the model skeleton, set up with the session."""
        if self._adapter is None:
            raise RuntimeError("no session opened on this connection")
        return self._adapter

    def finish(self) -> None:
        if self.direct is not None:
            self.direct.binary_sink = None
        if self._session is not None:
            self.log.info(
                "%s after frame %s",
                "ended" if self._session.ended else "disconnected (resumable)",
                self._session.last_seq,
            )
            self.rt.session_closed(self._session)
            if self.rt.connections.get(self._session.id) is self:
                del self.rt.connections[self._session.id]

    # ---- drain and snapshot acknowledgements ----------------------------------------
    async def stop_processing(self) -> None:
        """Drain, step 1: finish the current frame, process nothing more, queue the snapshot."""
        self.stopping = True
        self.wakeup.set()
        if self.processor is not None:
            await asyncio.gather(self.processor, return_exceptions=True)
        self.rt.session_closed(self.session)

    async def close_for_restart(self) -> None:
        """Drain, step 2 (the snapshot is stored): 1012 with the resume token in the reason."""
        await self.close(CLOSE_RESTART, f"service restart; resume_token={self.session.token}")

    def snapshot_saved(self, snap: Snapshot) -> None:
        """Tell the client frames up to `last_seq` are safe in the store (it may forget them)."""
        if self.stopping or snap.last_seq is None:
            return
        task = asyncio.get_running_loop().create_task(self._send_ack(snap.last_seq))
        self._send_tasks.add(task)
        task.add_done_callback(self._send_tasks.discard)

    async def _send_ack(self, last_seq: int) -> None:
        try:
            await self.send_json({"type": "snapshot", "last_seq": last_seq})
        except (WebSocketDisconnect, RuntimeError, OSError):  # the client left meanwhile: it has no use for it
            pass

    async def open(self, first: P.Start | P.CrowdStart) -> bool:
        if not isinstance(first, P.Start):
            raise TypeError("a session opens with a 'start' message")
        message = first
        try:
            model = self.rt.models.get(message.model)
            builds = self.rt.rig_builds  # rigs are built off the event loop
            if message.resume_token is None and model is not None:  # a bad rig opens no session at all
                self._adapter = await builds.adapter(
                    self.who.key,
                    message.skeleton or "custom",
                    message.bvh_header,
                    model.skeleton,
                    **message.rig_options(),
                )
            self._session = s = await self.rt.open_session(message, self.who)
            self.acks = message.snapshot_acks
            if self._adapter is None:  # a resume: the rig the session started with
                self._adapter = await builds.adapter(self.who.key, s.skeleton, s.bvh_header, s.model.skeleton, **s.rig)
        except P.ProtocolError as err:
            await self.refuse(err)
            return False
        s, adapter = self.session, self.adapter
        started = {
            "type": "started",
            "version": P.PROTOCOL_VERSION,
            "session_id": s.id,
            "resume_token": s.token,
            "model": pipelines.split(s.model.name)[0],
            "pipeline": pipelines.split(s.model.name)[1],
            "styles": s.model.styles(),
            "joints": adapter.joint_names,
            "last_seq": s.last_seq,
            "encoding": s.encoding,
            "layout": {
                "root": 3,
                "rotations": [adapter.num_joints, 4],
                "quaternion": "xyzw",
                "binary_frame_bytes": P.binary_frame_size(adapter.num_joints),
            },
            "rig": adapter.report(),  # the mapping used and the joints left unmapped
            "output_delay_ms": delay_ms(s.model.fps, s.fps),  # each reply: the model's output this long ago
        }
        if (
            message.resume_token and s.last_output and s.last_seq is not None
        ):  # the reply to last_seq, in case the client lost it
            started["last_frame"] = P.frame_message(s.last_seq, s.last_output["root"], s.last_output["rotations"])
        await self.send_json(started)
        self.rt.connections[s.id] = self
        direct = self.ws.scope.get("extensions", {}).get(DIRECT_FRAMES)
        if isinstance(direct, GuardedWebSocket) and s.encoding != "json":
            self.direct = direct
            direct.binary_sink = self.take_frame
        self.log = session_log(log, s.id, s.model.name)
        client = f"{self.ws.client.host}:{self.ws.client.port}" if self.ws.client else "?"
        self.log.info(
            "%s (client %s, rig %s)",
            f"resumed after frame {s.last_seq}" if message.resume_token else "started",
            client,
            adapter.report().get("preset", "custom"),
        )
        return True

    async def on_text_or_refresh(self, data: str) -> bool:
        """`on_text`; a `style` message naming a style this replica lacks first makes a replica that
        shares its styles folder look for it there (another replica may have just taken the upload)."""
        try:
            return self.on_text(data)
        except P.ProtocolError as err:
            styles = self.rt.styles
            if err.code != "unknown_style" or styles is None or not styles.shared:
                raise
            await styles.refresh()
            return self.on_text(data, admitted=True)  # the same message: counted once against the rate

    def on_text(self, data: str, admitted: bool = False) -> bool:
        message = P.parse_text(data)
        if isinstance(message, P.Start | P.CrowdStart):
            raise P.ProtocolError("already_started", "session already started", fatal=True)
        if isinstance(message, P.Join | P.Leave) or (
            isinstance(message, P.SetStyle | P.Reset) and message.characters is not None
        ):
            raise P.ProtocolError("not_a_crowd", "characters are named only on a crowd connection (see 'crowd')")
        if isinstance(message, P.Frame):
            root, rot = P.frame_arrays(message, self.adapter.num_joints)
            self.queue(FrameItem(message.seq, root, rot, time.perf_counter()))
            return True
        if isinstance(message, P.Control):
            self.queue(self.control_item(message))
            return True
        if not (admitted or isinstance(message, P.End)) and not self.control_rate.admit(time.monotonic()):
            return True  # style and reset messages over their own, lower rate: dropped (the first one told)
        if isinstance(message, P.SetStyle):  # validate now, so the error comes back at once
            self.rt.check_style(self.who, self.session.model.name, P.mix_of(message.style, message.mix))
            P.requested_weights(self.session.model, message.style, message.mix, message.intensity)
        self.queue(ControlItem(message))
        return not isinstance(message, P.End)

    def control_item(self, message: P.Control) -> FrameItem:
        """A controller tick as a frame whose input pose is the rest pose (a controller model
        reads the control, not the pose); refused at once on a model that takes no control."""
        if not self.session.model.controllable:
            raise P.ProtocolError(
                "control_unsupported",
                f"model {self.session.model.name!r} is not a character "
                "controller; send frames (controllable models: see GET /v1/models)",
                message.seq,
            )
        rest = np.zeros((self.adapter.num_joints, 4))
        rest[:, 3] = 1.0
        return FrameItem(message.seq, np.zeros(3), rest, time.perf_counter(), P.control_array(message))

    def on_binary(self, data: bytes) -> None:
        seq, root, rot = P.decode_binary(data, self.adapter.num_joints)
        self.queue(FrameItem(seq, root, rot, time.perf_counter()))

    def queue(self, item: FrameItem | ControlItem) -> None:
        s = self.session
        before = s.dropped_pending
        s.enqueue(item)
        if s.dropped_pending > before:
            self.model_metrics.dropped_frames.inc(s.dropped_pending - before)
        self.wakeup.set()

    # ---- processing -----------------------------------------------------------------
    async def process(self) -> None:
        s = self.session
        batcher = self.rt.batchers[s.model.name]
        while (item := await self.next_work(s.pending)) is not None:
            if isinstance(item, ControlItem):
                if not await self.control(item.message):
                    return
                continue
            began = time.perf_counter()
            root, rot = self.adapter.to_model(item.root, item.rotations, s.hinges)
            self.share.charge(time.perf_counter() - began)  # the receiver pauses for it (`LoopShare`)
            if gone := s.drop_deleted(s.model.styles()):
                await self.send_error(style_deleted(gone, item.seq))
            try:
                for step_root, step_rot in s.model_inputs(root, rot):  # rate adaptation: the model's own fps
                    out_root, out_rot, s.state = await batcher.step(
                        s.state, step_root, step_rot, s.advance_style(), item.control
                    )
                    s.hold(out_root, out_rot, root, rot)
            except Exception:  # noqa: BLE001 - a model failure costs this frame, not the session
                self.log.exception("model step failed")
                await self.send_error(step_failed(item.seq))
                continue
            began = time.perf_counter()
            reply = self.reply(item)
            if isinstance(reply, bytes):
                await self.send_bytes(reply)
            else:
                await self.send_json(reply)
            self.replied(item)
            self.share.charge(time.perf_counter() - began)

    def reply(self, item: FrameItem) -> bytes | dict:
        """The answer to a stepped frame, in the session's encoding; the session now stands at
        `item.seq`."""
        s = self.session
        out_root, out_rot = s.held_output()
        s.last_seq = item.seq
        out_root, out_rot = self.adapter.from_model(out_root, out_rot, item.rotations, s.hinges)
        s.last_output = {"root": out_root, "rotations": out_rot}
        dropped = s.take_dropped()
        if s.encoding == "binary":
            return P.encode_binary(item.seq, out_root, out_rot, dropped)
        fade = faded(s.state)
        value = None if fade is None else float(fade[0])
        if s.encoding == "binary-faded":  # a core pipeline has no fade: it never fades
            return P.encode_binary(item.seq, out_root, out_rot, dropped, 0.0 if value is None else value)
        return P.frame_message(item.seq, out_root, out_rot, dropped, value)

    def replied(self, item: FrameItem) -> None:
        metrics = self.model_metrics
        metrics.frame_latency.observe(time.perf_counter() - item.received)
        metrics.frames.inc()
        self.rt.after_frame(self.session, self.snapshot_saved if self.acks else None)

    @functools.cached_property
    def model_metrics(self) -> ModelMetrics:
        return self.metrics.model(self.session.model.name)

    # ---- the direct path (module doc) ----------------------------------------------------
    def take_frame(self, data: bytes) -> bool:
        """`GuardedWebSocket.binary_sink`: take a binary frame as the protocol parses it, if
        nothing is queued or in hand on either task and it is a frame the processor would step
        as is; False leaves it to the receiver (which answers a bad or rate-limited one)."""
        s, now = self.session, time.monotonic()
        if (
            self.direct_busy
            or not (self.receiving and self.parked)
            or self.closing
            or self.stopping
            or s.pending
            or len(data) > self.settings.max_message_bytes
            or not self.rate.would_admit(now)
            or s.styles_gone(s.model.styles())
        ):
            return False
        try:
            seq, root, rot = P.decode_binary(data, self.adapter.num_joints)
        except P.ProtocolError:
            return False
        self.rate.admit(now)
        self.heard, self.direct_busy = now, True
        self.model_metrics.direct_frames.inc()
        item = FrameItem(seq, root, rot, time.perf_counter())
        try:
            model_root, model_rot = self.adapter.to_model(root, rot, s.hinges)
            self._step_directly(item, model_root, model_rot, deque(s.model_inputs(model_root, model_rot)))
        except Exception:  # noqa: BLE001 - as in `process`: it costs this frame, not the session
            self._direct_failed(item)
        return True

    def _step_directly(self, item: FrameItem, root: np.ndarray, rot: np.ndarray, inputs: deque) -> None:
        """Step the model on each of `inputs` (this frame's model steps, `Session.model_inputs`),
        one batch at a time, then answer; `root`, `rot`: the frame on the model skeleton."""
        s = self.session
        if not inputs:
            self._answer_directly(item)
            return
        step_root, step_rot = inputs.popleft()
        future = self.rt.batchers[s.model.name].step_rows(s.state, step_root[None], step_rot[None], s.advance_style())
        future.add_done_callback(functools.partial(self._stepped, item, root, rot, inputs))

    def _stepped(
        self, item: FrameItem, root: np.ndarray, rot: np.ndarray, inputs: deque, future: asyncio.Future
    ) -> None:
        if future.cancelled():  # the batcher stopped: the server is going down
            self._direct_done()
            return
        try:
            out_root, out_rot, self.session.state = future.result()
            self.session.hold(out_root[0], out_rot[0], root, rot)
            self._step_directly(item, root, rot, inputs)
        except Exception:  # noqa: BLE001 - a model failure costs this frame, not the session
            self._direct_failed(item)

    def _direct_failed(self, item: FrameItem) -> None:
        self.log.exception("model step failed")
        self._send_then_done(self.send_error(step_failed(item.seq)))

    def _answer_directly(self, item: FrameItem) -> None:
        payload = self.reply(item)
        assert isinstance(payload, bytes)  # the direct path is offered to binary sessions only
        if self.send_lock.locked() or self.direct is None or not self.direct.write_binary(payload):
            self._send_then_done(self.send_bytes(payload), item)  # the peer is slow, or a send is under way
            return
        self.replied(item)
        self._direct_done()

    def _send_then_done(self, send: Coroutine[Any, Any, None], answered: FrameItem | None = None) -> None:
        """A reply the direct path cannot write at once: sent by a task, in order (nothing else
        of this session is taken before it has gone); `answered`: the frame it answers."""

        async def sending() -> None:
            try:
                await send
                if answered is not None:
                    self.replied(answered)
            except Exception:  # noqa: BLE001 - the client left meanwhile: the receiver sees its disconnect
                self.log.debug("direct reply not sent", exc_info=True)
            finally:
                self._direct_done()

        task = asyncio.get_running_loop().create_task(sending())
        self._send_tasks.add(task)
        task.add_done_callback(self._send_tasks.discard)

    def _direct_done(self) -> None:
        self.direct_busy = False
        if self.session.pending or self.closing or self.stopping:
            self.wakeup.set()  # the processor goes on with what came meanwhile (or ends)

    async def control(self, message: P.SetStyle | P.Reset | P.End) -> bool:
        s = self.session
        if isinstance(message, P.SetStyle):
            try:
                s.set_style(
                    P.requested_weights(s.model, message.style, message.mix, message.intensity),
                    message.transition_frames,
                )
            except P.ProtocolError as err:
                await self.send_error(err)
            else:
                await self.send_json(
                    {
                        "type": "style_set",
                        "weights": {k: s.target.get(k, 0.0) for k in s.model.styles()},
                        "transition_frames": message.transition_frames,
                    }
                )
            return True
        if isinstance(message, P.Reset):
            s.reset()
            await self.send_json({"type": "reset_done"})
            return True
        await self.send_json({"type": "ended", "session_id": s.id, "last_seq": s.last_seq})
        self.rt.session_ended(s)
        await self.close(CLOSE_NORMAL, "end")
        return False
