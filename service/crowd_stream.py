"""`WS /v1/stream` opened with `crowd` (protocol v1.1): many characters on one connection.

The client opens the crowd with its characters, then sends one binary tick per frame time
holding every listed character's frame; the server answers each tick with one binary reply
holding every character's stylised frame (`service.crowd`). Characters join and leave with
`join` and `leave`; `style` and `reset` name the characters they are for. A refused character
(bad rig, unknown style) or a refused frame (NaN, zero quaternion) costs that character alone: a
typed error naming it, and the others go on.

As for a session, the receiver only checks sizes and rates and queues; the processor takes the
queue in order, so a tick sent after a `join` always finds the character there. Ticks beyond
the queue bound push out the oldest tick (the next reply counts them in `dropped`).
"""

from __future__ import annotations

import asyncio
import json
import time
import uuid
from collections import deque

from . import pipelines
from . import protocol as P
from .background import in_background
from .crowd import Crowd, CrowdStep, Joining
from .logs import session_log
from .memory import release_freed_memory
from .pacing import SLICE_S, Pacer
from .skeletons import SkeletonAdapter
from .stream import CLOSE_NORMAL, CLOSE_RESTART, Socket, delay_ms, log

ControlMessage = P.Join | P.Leave | P.SetStyle | P.Reset | P.End
# characters snapshotted, added, or taken out at a time (~10 us each for LTI), `Pacer` between parts
PART = 32
TRIM_AFTER_CHARACTERS = 256  # a crowd this large leaves tens of MB freed in the heap when it closes
_closing: set[asyncio.Task] = set()  # held until done (the loop keeps only weak references)


class CrowdConnection(Socket):
    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.id = uuid.uuid4().hex
        self.crowd = Crowd(30.0)
        self.pending: deque[bytes | ControlMessage] = deque()
        self.ticks_pending = 0
        self.dropped = 0  # ticks dropped since the last reply
        self.opened = False
        self.last_seq: int | None = None  # the last tick answered (kept with the characters' snapshots)
        self.ticks_since_snapshot = 0
        self.ended = False  # the client said 'end': nothing to resume
        self.pacer = Pacer()  # all its bulk work: tick parts (`_step_for`), joins, snapshots, leaves

    # ---- opening, joining, leaving ------------------------------------------------------
    async def open(self, first: P.Start | P.CrowdStart) -> bool:
        if not isinstance(first, P.CrowdStart):
            raise TypeError("a crowd opens with a 'crowd' message")
        try:
            self.rt.open_crowd()
        except P.ProtocolError as err:
            await self.refuse(err)
            return False
        self.opened = True
        self.crowd = Crowd(first.fps, reserve=self.who.limits.max_characters, faded=first.faded)
        # each crowd's snapshots on a tick of its own (its id is random): crowds opened together
        # would otherwise all store every character on the same tick, stalling every stream at once
        self.ticks_since_snapshot = int(self.id, 16) % self.settings.snapshot_every
        self.rt.connections[self.id] = self
        self.log = session_log(log, self.id, "crowd")
        joined = await self.join(first.characters)
        delays = {name: delay_ms(t.model.fps, first.fps) for name, t in self.crowd.troupes.items()}
        await self.send_json(
            {
                "type": "crowd_started",
                "version": P.PROTOCOL_VERSION,
                "crowd_id": self.id,
                "output_delay_ms": delays,  # by model: each reply is its output this long ago
                **joined,
            }
        )
        self.log.info("crowd started with %d characters", len(self.crowd))
        return True

    async def join(self, specs: list[P.CrowdCharacter]) -> dict:
        """Check each character's request and add those that pass, in one go; each refusal is
        that character's alone. Returns the reply's `characters`, `rigs` and `errors`."""
        resuming: set[str] = set()  # claimed (`Runtime.resumable`): released once joined or refused
        try:
            return await self._join(specs, resuming)
        finally:
            for session_id in resuming:
                self.rt.resumed(session_id)

    async def _join(self, specs: list[P.CrowdCharacter], resuming: set[str]) -> dict:
        joining: list[Joining] = []
        errors: list[dict] = []
        adapters: dict[tuple, SkeletonAdapter] = {}
        seen = set(self.crowd.characters)
        pacer = self.pacer
        for spec in specs:
            await pacer.pace()
            try:
                if spec.id in seen:
                    raise P.ProtocolError("character_exists", f"character {spec.id} is already in this crowd")
                snap, skeleton = None, spec.skeleton
                if spec.resume_token is not None:  # model, style and rig as stored
                    snap = await self.rt.resumable(spec.resume_token, self.who)  # claimed (a second: in use)
                    resuming.add(snap.session_id)
                    model, weights = self.rt.pipeline(snap.model, snap.pipeline), dict(snap.weights)
                    skeleton, bvh_header, options = snap.skeleton, snap.bvh_header, dict(snap.rig)
                else:
                    model, weights = await self.rt.new_character(spec, self.who)
                    skeleton, bvh_header, options = spec.skeleton, spec.bvh_header, spec.rig_options()
                key = (model.name, skeleton, bvh_header, json.dumps(options, sort_keys=True))
                if key not in adapters:  # built off the event loop, within this caller's gate
                    adapters[key] = await self.rt.rig_builds.adapter(
                        self.who.key, skeleton or "custom", bvh_header, model.skeleton, **options
                    )
                joining.append(Joining(spec, model, key[1:], adapters[key], weights, snap))
                seen.add(spec.id)
            except P.ProtocolError as err:
                self.metrics.errors.labels(err.code).inc()
                errors.append({"id": spec.id, "code": err.code, "message": err.message})
        try:
            self.rt.add_characters(self.who, len(joining))
        except P.ProtocolError as err:
            self.metrics.errors.labels(err.code).inc()
            errors += [{"id": j.spec.id, "code": err.code, "message": err.message} for j in joining]
            joining = []
        for start in range(0, len(joining), PART):  # a large join lets other connections run between parts
            await pacer.pace()
            self.crowd.add(joining[start : start + PART])
        for j in joining:
            character = self.crowd.characters[j.spec.id]
            self.rt.crowd_members.add(character.session_id)
            self.rt.crowd_tokens.add(character.token)
            if j.resumed is not None:
                self.rt.character_resumed(self.who.id, character.token)
        rigs = list({id(j.adapter): j.adapter for j in joining}.values())
        rig_index = {id(a): k for k, a in enumerate(rigs)}
        return {
            "characters": [
                {
                    "id": j.spec.id,
                    "model": pipelines.split(j.model.name)[0],
                    "pipeline": pipelines.split(j.model.name)[1],
                    "rig": rig_index[id(j.adapter)],
                    "resume_token": self.crowd.characters[j.spec.id].token,
                    "resumed": j.resumed is not None,
                    "last_seq": j.resumed.last_seq if j.resumed is not None else None,
                }
                for j in joining
            ],
            "rigs": [
                {
                    "joints": a.joint_names,
                    "frame_floats": 3 + 4 * a.num_joints,
                    "rig": a.report(),
                }
                for a in rigs
            ],
            "errors": errors,
        }

    async def leave(self, ids: list[int], resumable: bool = False) -> list[int]:
        """Take characters out of the crowd: for good (`leave`, `end`), or `resumable` (their
        connection went), each then kept in the store under its resume token. In parts, paced
        (`Pacer`): 4,000 characters at once held every stream ~40 ms on the loaded 2-core machine."""
        present = [i for i in dict.fromkeys(ids) if i in self.crowd.characters]
        # the caller keeps at most `token_max_stored_sessions` closed: store only those (storing
        # all, then evicting all but those, stalled every stream for 733 ms at 16,384 characters)
        kept = set(present[max(0, len(present) - self.settings.token_max_stored_sessions) :] if resumable else [])
        for start in range(0, len(present), PART):
            await self.pacer.pace()
            part = present[start : start + PART]
            if stored := [i for i in part if i in kept]:
                self.rt.characters_stored(self.who.id, self.crowd.snapshots(self.who.tenant, self.last_seq, stored))
            for i in part:  # a resume of these finds `session_in_use` until here, then the snapshot just queued
                character = self.crowd.characters[i]
                self.rt.crowd_members.discard(character.session_id)
                self.rt.crowd_tokens.discard(character.token)
                self.rt.closing.discard(character.token)
                if i not in kept:
                    self.rt.character_ended(self.who.id, character.token)
            self.crowd.remove(part)
            self.rt.remove_characters(self.who, len(part))
        return present

    def finish(self) -> None:
        """The connection is over: its characters are stored or ended by a task, paced, the
        crowd's counts released as each part goes."""
        if not self.opened:
            return
        self.log.info("crowd closed with %d characters", len(self.crowd))
        if self.rt.connections.get(self.id) is self:
            del self.rt.connections[self.id]
        # until each is stored (or ended), a resume of its token is told to try again, not that it is unknown
        self.rt.closing.update(c.token for c in self.crowd.characters.values())
        closing = asyncio.get_running_loop().create_task(self._close())
        _closing.add(closing)
        closing.add_done_callback(_closing.discard)

    async def _close(self) -> None:
        large = len(self.crowd) >= TRIM_AFTER_CHARACTERS
        try:
            await self.leave(list(self.crowd.characters), resumable=not self.ended)
        finally:
            left = [c.token for c in self.crowd.characters.values()]  # any a failed leave left behind
            self.rt.closing.difference_update(left)
            self.rt.crowd_tokens.difference_update(left)
            self.rt.crowd_closed()
        if large:  # its arrays went back to the heap: hand the pages to the system (off the loop)
            await in_background(release_freed_memory)

    # ---- receiving ----------------------------------------------------------------------
    def on_binary(self, data: bytes) -> None:
        if self.ticks_pending >= self.settings.session_queue:  # the newest ticks win; memory stays bounded
            oldest = next(i for i, item in enumerate(self.pending) if isinstance(item, bytes))
            del self.pending[oldest]
            self.ticks_pending -= 1
            self.dropped += 1
            for name, troupe in self.crowd.troupes.items():
                self.metrics.model(name).dropped_frames.inc(len(troupe))
        self.pending.append(data)
        self.ticks_pending += 1
        self.wakeup.set()

    async def on_text_or_refresh(self, data: str) -> bool:
        message = P.parse_text(data)
        if isinstance(message, P.Start | P.CrowdStart):
            raise P.ProtocolError("already_started", "crowd already started", fatal=True)
        if isinstance(message, P.Frame | P.Control):
            raise P.ProtocolError("bad_message", "a crowd sends binary ticks (kind 2), not 'frame' or 'control'")
        if not isinstance(message, P.End) and not self.control_rate.admit(time.monotonic()):
            return True  # over the control-message rate: dropped (the first one told)
        if sum(not isinstance(i, bytes) for i in self.pending) >= self.settings.session_queue:
            raise P.ProtocolError(
                "queue_full", f"{self.settings.session_queue} control messages are already waiting; send it again later"
            )
        self.pending.append(message)
        self.wakeup.set()
        return not isinstance(message, P.End)

    # ---- processing ---------------------------------------------------------------------
    def _step_for(self, model: str) -> CrowdStep:
        """The batcher's entry for this crowd's parts of `model`, paced: before each part, once
        the crowd's work has run its slice, it pauses (`Pacer`). Back to back, a crowd's ticks kept
        the event loop busy without a break: a session's frame, a few loop passes to answer,
        waited behind a part at each, and the loop's thread, never asleep, lost the scheduler's
        favour on a busy machine (a neighbour's median round trip 1.5 -> 7-11 ms under a
        712-character tick stream). Each part is as many rows as the model steps in a slice
        (`Batcher.part_rows`)."""
        batcher = self.rt.batchers[model]

        async def step(state, root, rot, weights, names, control):  # noqa: ANN001, ANN202 - StepRows
            await self.pacer.pace()
            return await batcher.step_rows(state, root, rot, weights, control, names)

        return CrowdStep(step, batcher.part_rows(SLICE_S))

    async def process(self) -> None:
        while (item := await self.next_work(self.pending)) is not None:
            if isinstance(item, bytes):
                self.ticks_pending -= 1
                await self.tick(item)
            elif not await self.control(item):
                return

    async def tick(self, data: bytes) -> None:
        received = time.perf_counter()
        try:
            seq, kind, ids_raw, payload = P.decode_tick(data)
            result = await self.crowd.tick(
                seq, ids_raw, payload, self._step_for, self.dropped, control=kind == P.KIND_CONTROL_TICK
            )
            self.dropped = 0  # told in this reply (a refused tick gets none: the next reply tells)
            self.last_seq = seq
        except P.ProtocolError as err:
            await self.send_error(err)
            return
        except Exception:  # noqa: BLE001 - a model failure costs this tick, not the crowd
            self.log.exception("crowd tick failed")
            await self.send_error(P.ProtocolError("internal", "model step failed", int.from_bytes(data[:4], "little")))
            return
        for refused in result.errors:
            await self.send_error(refused)
        await self.send_bytes(result.reply)
        for name, frames in result.frames.items():
            metrics = self.metrics.model(name)
            metrics.frames.inc(frames)
            metrics.frame_latency.observe(time.perf_counter() - received)
        await self.store_some()

    async def store_some(self) -> None:
        """Every `snapshot_every` ticks (as a session: for a replica that dies) every character,
        as they all stood after the same tick: a resumed crowd's client replays from one
        `last_seq` for all of them. Built by this crowd's processor, PART characters at a time,
        paced (`Pacer`): its own next tick waits, so no character moves meanwhile, and other
        connections run between parts. (Copying the crowd first held every stream 13 ms at 4,000
        LTI characters, building all the snapshots at once ~100 ms.) Each crowd at a phase of its
        own (`open`)."""
        self.ticks_since_snapshot += 1
        if self.ticks_since_snapshot < self.settings.snapshot_every or not len(self.crowd):
            return
        self.ticks_since_snapshot = 0
        ids = list(self.crowd.characters)
        for start in range(0, len(ids), PART):
            await self.pacer.pace()
            if self.stopping:  # the connection went: its close stores them as they stand
                return
            for snap in self.crowd.snapshots(self.who.tenant, self.last_seq, ids[start : start + PART]):
                self.rt.snapshots.put(snap)

    async def control(self, message: ControlMessage) -> bool:
        if isinstance(message, P.Join):
            await self.send_json({"type": "joined", **await self.join(message.characters)})
        elif isinstance(message, P.Leave):
            await self.send_json({"type": "left", "characters": await self.leave(message.characters)})
        elif isinstance(message, P.SetStyle | P.Reset):
            await self.restyle_or_reset(message)
        else:
            self.ended = True
            await self.leave(list(self.crowd.characters))  # all gone, nothing to resume, once it is told
            await self.send_json({"type": "ended", "session_id": self.id, "last_seq": self.last_seq})
            await self.close(CLOSE_NORMAL, "end")
            return False
        return True

    async def restyle_or_reset(self, message: P.SetStyle | P.Reset) -> None:
        ids = list(self.crowd.characters) if message.characters is None else list(dict.fromkeys(message.characters))
        unknown = [i for i in ids if i not in self.crowd.characters]
        if unknown:
            await self.send_error(
                P.ProtocolError("unknown_character", f"no character {', '.join(map(str, unknown[:10]))} in this crowd")
            )
            return
        troupes = self.crowd.troupe_rows(ids)
        if isinstance(message, P.Reset):
            for troupe, rows, _ in troupes.values():
                troupe.reset(rows)
            await self.send_json({"type": "reset_done", "characters": ids})
            return
        try:  # every model of the named characters must know the style, or none changes
            targets = {}
            for name, (troupe, _, _) in troupes.items():
                await self.rt.styles.ensure_known(pipelines.split(name)[0], P.mix_of(message.style, message.mix))
                self.rt.check_style(self.who, name, P.mix_of(message.style, message.mix))
                targets[name] = P.requested_weights(troupe.model, message.style, message.mix, message.intensity)
        except P.ProtocolError as err:
            await self.send_error(err)
            return
        for name, (troupe, rows, _) in troupes.items():
            troupe.set_style(rows, targets[name], message.transition_frames)
        await self.send_json(
            {
                "type": "style_set",
                "characters": ids,
                "weights": {name: targets[name] for name in targets},
                "transition_frames": message.transition_frames,
            }
        )

    # ---- drain ----------------------------------------------------------------------------
    async def stop_processing(self) -> None:
        """Drain, step 1: finish the current tick, then store every character for resume."""
        self.stopping = True
        self.wakeup.set()
        if self.processor is not None:
            await asyncio.gather(self.processor, return_exceptions=True)
        if not self.ended:
            await self.leave(list(self.crowd.characters), resumable=True)

    async def close_for_restart(self) -> None:
        await self.close(CLOSE_RESTART, "service restart; open the crowd again with the characters' resume tokens")
