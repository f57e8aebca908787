"""Cross-session batching: frames of many sessions run as one `step_batch` call.

Each session has at most one frame in flight (its processor awaits the reply before taking the
next), so a batch never holds two frames of one session. The batcher waits at most `wait_s`
after the first frame for others to join, or until `max_batch` are gathered, then runs the step
on a worker thread (keeping the event loop free) and scatters the results back.

The model's style set may change between steps (style changes run on the same worker thread), so
the step, on that thread, first brings every session's state to the current style set
(`upgrade_state`) and builds the weight vectors over the current `styles()` from each session's
`{style: weight}` dict.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from concurrent.futures import Executor
from dataclasses import dataclass

import numpy as np

from models.interface import FrameBatch, State, StreamingModel, split_state, stack_states, upgrade_state, weight_vector

from .metrics import Metrics


@dataclass
class StepRequest:
    state: State
    root: np.ndarray
    rotations: np.ndarray
    weights: dict[str, float]  # {style: weight}
    future: asyncio.Future
    control: np.ndarray | None = None  # (5,) a controller tick, see `FrameBatch.control`


def run_step(model: StreamingModel, requests: list[StepRequest]) -> list[tuple[np.ndarray, np.ndarray, State]]:
    """One batched step over the requests' sessions; pure, runs on the worker thread."""
    state = stack_states([upgrade_state(model, r.state) for r in requests])
    control = None
    if any(r.control is not None for r in requests):  # rows without control: flag 0, follow the input frames
        control = np.stack([r.control if r.control is not None else np.zeros(5) for r in requests])
    frames = FrameBatch(np.stack([r.root for r in requests]), np.stack([r.rotations for r in requests]), control=control)
    names = model.styles()
    out, new_state = model.step_batch(state, frames, np.stack([weight_vector(names, r.weights) for r in requests]))
    states = split_state(new_state)
    return [(out.root[i], out.rotations[i], states[i]) for i in range(len(requests))]


class Batcher:
    def __init__(self, model: StreamingModel, executor: Executor, metrics: Metrics,
                 wait_s: float = 0.001, max_batch: int = 256, enabled: bool = True,
                 open_sessions: Callable[[], int] | None = None) -> None:
        self.model, self.executor, self.metrics = model, executor, metrics
        self.wait_s, self.max_batch = wait_s, (max_batch if enabled else 1)
        # a batch is full once every open session of this model is in it: waiting longer gains nothing
        self.open_sessions = open_sessions or (lambda: self.max_batch)
        self.queue: asyncio.Queue[StepRequest] = asyncio.Queue()
        self._task: asyncio.Task | None = None

    def start(self) -> None:
        self._task = asyncio.get_running_loop().create_task(self._run(), name=f"batcher-{self.model.name}")

    async def stop(self) -> None:
        if self._task:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)

    async def step(self, state: State, root: np.ndarray, rotations: np.ndarray, weights: dict[str, float],
                   control: np.ndarray | None = None):
        future = asyncio.get_running_loop().create_future()
        await self.queue.put(StepRequest(state, root, rotations, weights, future, control))
        return await future

    async def _gather(self) -> list[StepRequest]:
        batch = [await self.queue.get()]
        deadline = time.monotonic() + self.wait_s
        full = min(self.max_batch, max(1, self.open_sessions()))
        while len(batch) < full:
            try:
                batch.append(self.queue.get_nowait())
                continue
            except asyncio.QueueEmpty:
                pass
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            try:
                batch.append(await asyncio.wait_for(self.queue.get(), remaining))
            except TimeoutError:
                break
        return batch

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        name = self.model.name
        while True:
            batch = await self._gather()
            t0 = time.perf_counter()
            try:
                results = await loop.run_in_executor(self.executor, run_step, self.model, batch)
            except Exception as exc:  # a model failure fails this batch's frames, never the batcher
                for req in batch:
                    if not req.future.done():
                        req.future.set_exception(exc)
                continue
            self.metrics.step_latency.labels(name).observe(time.perf_counter() - t0)
            self.metrics.batch_size.labels(name).observe(len(batch))
            for req, result in zip(batch, results):
                if not req.future.done():
                    req.future.set_result(result)
