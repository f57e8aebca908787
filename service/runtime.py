"""Process-wide runtime: loaded models, one batcher per model, the worker thread, sessions and
the snapshot store. The FastAPI app holds one of these; tests may run several side by side.

Sessions are snapshotted every `snapshot_every` frames and when their connection goes, through a
background `SnapshotWriter`, so a client can resume here or on any replica sharing the store.
`drain` (SIGTERM) refuses new sessions, snapshots every open one and closes it with 1012.

The runtime is given the models, the worker thread and the style store, built before it (the
app's lifespan): a model whose style set can change is this server's own copy
(`models.interface.own_style_set`), so the styles its store adds or removes (on the worker
thread) stay its own even when several servers share one process. Beside them it may be given
each method's published core alone (`service.pipelines`): `pipelines` holds both under their
keys, and batchers, session counts and snapshots go by those keys.
"""

from __future__ import annotations

import asyncio
import secrets
import time
from collections import Counter, OrderedDict
from collections.abc import Callable, Iterable
from typing import Any, Protocol, TypeVar

import numpy as np

from models.interface import FrameBatch, StreamingModel, weight_vector
from models.motion import rate_kernels

from . import frame_check, pipelines, skeletons
from . import protocol as P
from .batcher import Batcher, ModelThread
from .limits import Principal
from .metrics import Metrics
from .rig_builds import RigBuilds
from .session_store import SavedCallback, SnapshotWriter, StoreUnavailable, create_store
from .sessions import Session, Snapshot
from .settings import ServiceSettings
from .styles import StyleStore

T = TypeVar("T")
MAX_STORED_CALLERS = 10_000  # above this, callers none of whose closed sessions can still be resumed are forgotten


class Drainable(Protocol):
    """A live connection as `drain` sees it (`stream.Connection`)."""

    async def stop_processing(self) -> None: ...
    async def close_for_restart(self) -> None: ...


def warm_up(model: StreamingModel) -> None:
    """One throwaway step on a rest pose: a model's first step pays lazy initialisation (LTI:
    ~0.7 s), which would otherwise stall the first session here, a resumed one included."""
    rotations = np.zeros((1, len(model.skeleton.names), 4))
    rotations[..., 3] = 1.0
    styles = model.styles()
    model.step_batch(
        model.init_state(1),
        FrameBatch(np.zeros((1, 3)), rotations),
        np.stack([weight_vector(styles, {styles[0]: 1.0} if styles else {})]),
    )


class Runtime:
    def __init__(
        self,
        settings: ServiceSettings,
        models: dict[str, StreamingModel],
        model_thread: ModelThread,
        styles: StyleStore,
        cores: dict[str, StreamingModel] | None = None,
    ) -> None:
        self.settings, self.models, self.model_thread, self.styles = settings, models, model_thread, styles
        # every pipeline served, by key (`pipelines.key`): the full ones (`models`) and the cores
        self.pipelines: dict[str, StreamingModel] = {**models, **(cores or {})}
        self.metrics = Metrics()
        self.batchers = {
            name: Batcher(
                model,
                self.model_thread,
                self.metrics,
                wait_s=settings.batch_wait_ms / 1000,
                max_batch=settings.max_batch,
                enabled=settings.batching,
                open_sessions=self._counter(name),
                inline_max_s=settings.step_inline_max_ms / 1000,
            )
            for name, model in self.pipelines.items()
        }
        self.sessions: dict[str, Session] = {}
        self._stored: dict[str, OrderedDict[str, float]] = {}  # caller id -> resume token -> closed at
        self._ttl = settings.resume_ttl_s
        self._open_per_model: Counter[str] = Counter()
        self.connections: dict[str, Drainable] = {}  # by session id (a crowd: by crowd id)
        self.crowds = 0  # open crowd connections
        self.characters = 0  # characters in them
        self._characters_of: Counter[str] = Counter()  # by caller (`Principal.key`), against its own cap
        self.crowd_members: set[str] = set()  # the session ids of those characters (resumes check it)
        self.resuming: set[str] = set()  # session ids claimed by a resume not yet registered
        self.closing: set[str] = set()  # resume tokens of crowd characters whose connection is being closed
        self.crowd_tokens: set[str] = set()  # resume tokens of the crowd characters connected now
        self.replica_id = secrets.token_hex(8)  # this process, in a shared store's resume claims
        self.snapshots = SnapshotWriter(create_store(settings.session_store, settings.resume_ttl_s), self.metrics)
        # rigs parsed and built in child processes, per caller
        self.rig_builds = RigBuilds(
            answered=lambda idle: self.metrics.rig_builds.labels("idle" if idle else "normal").inc()
        )
        self.draining = False

    async def start(self) -> None:
        frame_check.warm()
        rate_kernels.warm()
        await self.on_model_thread(skeletons.warm)
        for model in self.pipelines.values():
            await self.on_model_thread(warm_up, model)
        for batcher in self.batchers.values():
            batcher.start()
        self.snapshots.start()

    async def stop(self) -> None:
        await asyncio.gather(*(b.stop() for b in self.batchers.values()))
        # what a drain could not save is retried this long (the drain's budget ends here too)
        await self.snapshots.stop(timeout_s=min(2.0, 0.1 * self.settings.drain_timeout_s))
        self.model_thread.shutdown()
        self.rig_builds.close()

    async def drain(self, timeout_s: float) -> None:
        """Refuse new sessions, stop every session after its current frame, save its snapshot,
        and only then close it with 1012, so its client finds the snapshot wherever it
        reconnects. Bounded by `timeout_s`: a store that does not answer delays the closes by at
        most that (the clients replay from their last acknowledged snapshot then)."""
        deadline = time.monotonic() + timeout_s
        self.draining = True
        connections = list(self.connections.values())
        stopping = asyncio.gather(*(c.stop_processing() for c in connections), return_exceptions=True)
        try:
            await asyncio.wait_for(stopping, timeout=0.5 * timeout_s)
        except TimeoutError:
            pass
        await self.snapshots.flush(max(0.0, deadline - time.monotonic() - 0.1 * timeout_s))
        await asyncio.gather(*(c.close_for_restart() for c in connections), return_exceptions=True)

    async def on_model_thread(self, fn: Callable[..., T], *args: Any) -> T:
        """`fn(*args)` on the model-step worker thread, between batched steps (style changes)."""
        return await self.model_thread.run(fn, *args)

    # ---- sessions -------------------------------------------------------------
    def open_sessions(self, model: str) -> int:
        """Open sessions of `model` (crowds are not counted: `service.batcher`); read by its batcher
        once per batch, so kept as a count."""
        return self._open_per_model[model]

    def _counter(self, model: str) -> Callable[[], int]:
        return lambda: self.open_sessions(model)

    def _refuse_if_draining(self) -> None:
        if self.draining:
            raise P.ProtocolError(
                "draining",
                "this replica is shutting down; connect again (another replica takes the session)",
                close_code=1012,
            )

    def full(self) -> bool:
        """Every one of `max_sessions` taken (a crowd connection takes one): readiness says so."""
        return len(self.sessions) + self.crowds >= self.settings.max_sessions

    def _refuse_if_full(self) -> None:
        """Draining, or every one of `max_sessions` taken (a crowd connection takes one)."""
        self._refuse_if_draining()
        if self.full():
            raise P.ProtocolError(
                "too_many_sessions",
                f"server holds its maximum of {self.settings.max_sessions} sessions",
                close_code=1013,
            )

    def offered(self, model: str) -> list[pipelines.Pipeline]:
        """The pipelines this server serves of `model` (GET /v1/models)."""
        return [p for p in pipelines.PIPELINES if pipelines.key(model, p) in self.pipelines]

    def pipeline(self, model: str, pipeline: str) -> StreamingModel:
        """The served `pipeline` of `model`, or the typed error that refuses it."""
        found = self.pipelines.get(pipelines.key(model, pipeline))
        if found is not None:
            return found
        if model in self.models:
            raise P.ProtocolError(
                "pipeline_unavailable",
                f"model {model!r} is served here with pipeline(s) {', '.join(self.offered(model))}, not {pipeline!r}",
            )
        raise P.ProtocolError(
            "unknown_model", f"unknown model {model!r}; available: {', '.join(self.models) or 'none'}"
        )

    async def new_character(self, spec: P.CharacterSpec, who: Principal) -> tuple[StreamingModel, dict[str, float]]:
        """The pipeline and starting {style: weight} a new session or crowd character asks for,
        or the typed error that refuses it (an unknown model or pipeline, or a style unknown, not
        `who`'s, or not in that pipeline)."""
        model = self.pipeline(spec.model, spec.pipeline)
        mix = P.mix_of(spec.style, spec.mix)
        await self.styles.ensure_known(spec.model, mix)
        self.check_style(who, model.name, mix)
        return model, P.requested_weights(model, spec.style, spec.mix, spec.intensity)

    async def resumable(self, token: str, who: Principal) -> Snapshot:
        """The snapshot `token` names, if `who` may take it up here (a session's, or a crowd
        character's: either resumes as either); a snapshot another tenant opened is, to them, as
        unknown as an expired one."""
        if token in self.closing:  # its closing crowd has not stored it yet: neither gone nor resumable
            raise P.ProtocolError("session_in_use", "that session's connection is still closing; try again")
        if token in self.crowd_tokens:  # its crowd's dropped connection is not noticed yet: nothing stored
            raise P.ProtocolError("session_in_use", "that session is still connected")
        try:
            snap = await self.snapshots.get(token)
        except StoreUnavailable:
            raise P.ProtocolError(
                "store_unavailable", "the session store cannot be reached; try again", close_code=1013
            ) from None
        if snap is None or snap.owner != who.tenant:
            raise P.ProtocolError("unknown_resume_token", "resume token unknown or expired")
        self.pipeline(snap.model, snap.pipeline)  # served here, or unknown_model / pipeline_unavailable
        await self.styles.ensure_known(snap.model, [*snap.weights, *snap.target])
        # checked after the last await, with nothing awaited until it is claimed: two resumes of
        # one token at once both passed a check made before an await, and both opened
        self._refuse_if_draining()
        if (
            snap.session_id in self.sessions
            or snap.session_id in self.crowd_members
            or snap.session_id in self.resuming
        ):
            raise P.ProtocolError("session_in_use", "that session is still connected")
        self.resuming.add(snap.session_id)  # the caller registers it, then `resumed`; or `resume_failed`
        try:  # and against another replica's resume of it at the same moment (a shared store)
            claimed = await self.snapshots.claim(token, self.replica_id)
        except StoreUnavailable:  # a store this replica cannot reach: its own snapshot still resumes here
            claimed = True
        if not claimed:
            self.resuming.discard(snap.session_id)
            raise P.ProtocolError("session_in_use", "that session is being resumed on another replica")
        return snap

    def resumed(self, session_id: str) -> None:
        """A claimed resume is registered (a session, or a crowd member) or given up."""
        self.resuming.discard(session_id)

    async def open_session(self, start: P.Start, who: Principal) -> Session:
        """A new session for `who`, or theirs resumed (a snapshot another tenant opened is, to
        them, as unknown as an expired one)."""
        self._refuse_if_full()
        if start.resume_token:
            snap = await self.resumable(start.resume_token, who)
            try:
                session = Session.restore(
                    snap, self.pipelines[pipelines.key(snap.model, snap.pipeline)], self.settings.session_queue, who.id
                )
            finally:
                self.resumed(snap.session_id)  # registered below, with no await in between
            self._forget_stored(session.caller, session.token)
            self.metrics.resumes.inc()
        else:
            model, weights = await self.new_character(start, who)
            session = Session(
                model=model,
                skeleton=start.skeleton or "custom",
                fps=start.fps,
                encoding=start.encoding,
                weights=weights,
                target=dict(weights),
                state=model.init_state(1),
                bvh_header=start.bvh_header,
                rig=start.rig_options(),
                queue_size=self.settings.session_queue,
                owner=who.tenant,
                caller=who.id,
            )
        self.sessions[session.id] = session
        self._open_per_model[session.model.name] += 1
        self.metrics.active_sessions.labels(session.model.name).inc()
        return session

    # ---- crowds (protocol v1.1) -------------------------------------------------------
    def open_crowd(self) -> None:
        """A crowd connection takes one of the server's `max_sessions` (its characters count
        against `max_characters`)."""
        self._refuse_if_full()
        self.crowds += 1

    def crowd_closed(self) -> None:
        self.crowds -= 1

    def add_characters(self, who: Principal, count: int) -> None:
        """Room for `count` more crowd characters of `who`: within the server's `max_characters`
        and the caller's own cap (`token_max_characters`), or `too_many_characters`."""
        if self.characters + count > self.settings.max_characters:
            raise P.ProtocolError(
                "too_many_characters",
                f"server holds its maximum of {self.settings.max_characters} crowd characters "
                f"({self.characters} now); {count} more do not fit",
            )
        held = self._characters_of[who.key]
        if held + count > who.limits.max_characters:
            holder = "this token" if who.key.startswith("token:") else "this client address"
            raise P.ProtocolError(
                "too_many_characters",
                f"{holder} holds its maximum of {who.limits.max_characters} crowd characters "
                f"({held} now); {count} more do not fit",
            )
        self.characters += count
        self._characters_of[who.key] += count

    def remove_characters(self, who: Principal, count: int) -> None:
        self.characters -= count
        self._characters_of[who.key] -= count
        if self._characters_of[who.key] <= 0:
            del self._characters_of[who.key]

    def check_style(self, who: Principal, name: str, names: Iterable[str]) -> None:
        """`check_visible` for the pipeline keyed `name`; and a core offers its method's built-in
        styles only: an uploaded style there is `style_not_in_pipeline`, not unknown."""
        model, pipeline = pipelines.split(name)
        names = list(names)
        self.check_visible(who, model, names)
        served = self.pipelines.get(name)
        full = self.models.get(model)
        if pipeline == "full" or served is None or full is None:
            return
        missing = sorted((set(names) - set(served.styles())) & set(full.styles()))
        if missing:
            raise P.ProtocolError(
                "style_not_in_pipeline",
                f"style(s) {', '.join(missing)} of model {model!r} are uploaded styles, made for its full "
                f"pipeline; the core pipeline has its built-in styles {', '.join(served.styles())}",
            )

    def check_visible(self, who: Principal, model: str, names: Iterable[str]) -> None:
        """Another tenant's uploaded style is, to `who`, a style that does not exist."""
        hidden = sorted(set(names) & self.styles.hidden_from(who, model))
        if hidden:
            raise P.ProtocolError("unknown_style", f"unknown style(s) {', '.join(hidden)} for model {model!r}")

    def after_frame(self, session: Session, on_saved: SavedCallback | None = None) -> None:
        """Called after each stylised frame's reply; queues a snapshot every `snapshot_every`."""
        if session.snapshot_due(self.settings.snapshot_every):
            self.snapshots.put(session.snapshot(), on_saved)

    def session_closed(self, session: Session) -> None:
        """Connection gone (or dropped): keep a snapshot so the client can resume."""
        if self.sessions.pop(session.id, None) is not None:
            self._open_per_model[session.model.name] -= 1
            self.metrics.active_sessions.labels(session.model.name).dec()
            if not session.ended:
                self.snapshots.put(session.snapshot())
                self._keep_stored(session.caller, session.token)

    def characters_stored(self, caller: str, snaps: list[Snapshot]) -> None:
        """A crowd's characters left with their connection: each kept for resume like a session,
        and counted like one against `caller`'s `token_max_stored_sessions`."""
        for snap in snaps:
            self.snapshots.put(snap)
            self._keep_stored(caller, snap.token)

    def _keep_stored(self, caller: str, token: str) -> None:
        """Count a closed session against its caller's `token_max_stored_sessions`; beyond it, that
        caller's oldest closed session is forgotten, so one client's churn never pushes another's
        snapshot out of a full store."""
        now = time.monotonic()
        if len(self._stored) > MAX_STORED_CALLERS:  # callers come and go: forget those whose snapshots expired
            self._stored = {c: k for c, k in self._stored.items() if next(reversed(k.values())) > now - self._ttl}
        kept = self._stored.setdefault(caller, OrderedDict())
        kept[token] = now
        kept.move_to_end(token)
        while kept and next(iter(kept.values())) < now - self._ttl:  # expired in the store by now
            kept.popitem(last=False)
        while len(kept) > self.settings.token_max_stored_sessions:
            oldest, _ = kept.popitem(last=False)
            self.snapshots.delete(oldest)
            self.metrics.errors.labels("stored_session_evicted").inc()

    def _forget_stored(self, caller: str, token: str) -> None:
        """A session (or crowd character) resumed or ended is no longer waiting in the store."""
        kept = self._stored.get(caller)
        if kept is not None:
            kept.pop(token, None)
            if not kept:
                del self._stored[caller]

    def character_resumed(self, caller: str, token: str) -> None:
        self._forget_stored(caller, token)
        self.metrics.resumes.inc()

    def character_ended(self, caller: str, token: str) -> None:
        """A crowd character that left (or whose crowd ended): nothing to resume."""
        self.snapshots.delete(token)
        self._forget_stored(caller, token)

    def session_ended(self, session: Session) -> None:
        """The client said 'end': nothing to resume."""
        session.ended = True
        self.snapshots.delete(session.token)
        self._forget_stored(session.caller, session.token)
