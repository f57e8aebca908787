"""Process-wide runtime: loaded models, one batcher per model, the worker thread, sessions and
the snapshot store. The FastAPI app holds one of these; tests may run several side by side.

A model whose style set can change (`add_style`) is taken as a shallow copy, so styles added to
or removed from this runtime's model (on the worker thread, `on_model_thread`) stay its own.
"""

from __future__ import annotations

import asyncio
from collections import Counter
import copy
from concurrent.futures import ThreadPoolExecutor

from models.interface import StreamingModel

from . import protocol as P
from .batcher import Batcher
from .metrics import Metrics
from .sessions import Session, SessionStore
from .settings import ServiceSettings


class Runtime:
    def __init__(self, settings: ServiceSettings, models: dict[str, StreamingModel]) -> None:
        self.settings = settings
        self.models = {name: copy.copy(m) if hasattr(m, "add_style") else m for name, m in models.items()}
        self.metrics = Metrics()
        self.executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="model-step")
        self.batchers = {name: Batcher(model, self.executor, self.metrics, wait_s=settings.batch_wait_ms / 1000,
                                       max_batch=settings.max_batch, enabled=settings.batching,
                                       open_sessions=lambda name=name: self.open_sessions(name))
                         for name, model in self.models.items()}
        self.sessions: dict[str, Session] = {}
        self._open_per_model: Counter[str] = Counter()
        self.store = SessionStore(ttl_s=settings.resume_ttl_s)

    async def start(self) -> None:
        for batcher in self.batchers.values():
            batcher.start()

    async def stop(self) -> None:
        await asyncio.gather(*(b.stop() for b in self.batchers.values()))
        self.executor.shutdown(wait=False, cancel_futures=True)

    async def on_model_thread(self, fn, *args):
        """`fn(*args)` on the model-step worker thread, between batched steps (style changes)."""
        return await asyncio.get_running_loop().run_in_executor(self.executor, fn, *args)

    # ---- sessions -------------------------------------------------------------
    def open_sessions(self, model: str) -> int:
        """Open sessions of `model`; read by its batcher once per batch, so kept as a count."""
        return self._open_per_model[model]

    def open_session(self, start: P.Start) -> Session:
        if len(self.sessions) >= self.settings.max_sessions:
            raise P.ProtocolError("too_many_sessions", f"server holds its maximum of {self.settings.max_sessions} sessions",
                                  close_code=1013)
        if start.resume_token:
            snap = self.store.get(start.resume_token)
            if snap is None:
                raise P.ProtocolError("unknown_resume_token", "resume token unknown or expired")
            if snap.session_id in self.sessions:
                raise P.ProtocolError("session_in_use", "that session is still connected")
            session = Session.restore(snap, self.models[snap.model], self.settings.session_queue)
        else:
            model = self.models.get(start.model)
            if model is None:
                raise P.ProtocolError("unknown_model", f"unknown model {start.model!r}; available: {', '.join(self.models) or 'none'}")
            weights = P.requested_weights(model, start.style, start.mix, start.intensity)
            session = Session(model=model, skeleton=start.skeleton or "custom", fps=start.fps, encoding=start.encoding,
                              weights=weights, state=model.init_state(1), bvh_header=start.bvh_header,
                              queue_size=self.settings.session_queue)
        self.sessions[session.id] = session
        self._open_per_model[session.model.name] += 1
        self.metrics.active_sessions.labels(session.model.name).inc()
        return session

    def after_frame(self, session: Session) -> None:
        if session.last_seq is not None and (session.last_seq + 1) % self.settings.snapshot_every == 0:
            self.store.put(session.snapshot())

    def session_closed(self, session: Session) -> None:
        """Connection gone (or dropped): keep a snapshot so the client can resume."""
        if self.sessions.pop(session.id, None) is not None:
            self._open_per_model[session.model.name] -= 1
            self.metrics.active_sessions.labels(session.model.name).dec()
            if not session.ended:
                self.store.put(session.snapshot())

    def session_ended(self, session: Session) -> None:
        """The client said 'end': nothing to resume."""
        session.ended = True
        self.store.delete(session.token)
