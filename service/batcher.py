"""Cross-session batching: frames of many sessions run as one `step_batch` call.

Each session has at most one frame in flight (its processor awaits the reply before taking the
next), so a batch never holds two frames of one session. The batcher waits at most `wait_s`
after the first frame for others to join, or until every open session of the model has one in,
then runs the step and scatters the results back (one future per frame, nothing else per frame:
no queue, no task, no timer per frame).

Where the step runs: model steps and style changes share one worker thread (`ModelThread`), so
a style change never runs in the middle of a step. A step predicted to take less than
`inline_max_s` runs right on the event loop when that thread is idle: the compiled step kernels
hold the GIL, so handing a short step to the thread only adds two thread switches and a wait for
the GIL; a long one goes to the thread, which lets the event loop in between kernels.

The model's style set may change between steps, so the step first brings every session's state
to the current style set (`upgrade_state`) and builds the weight vectors over the current
`styles()` from each session's `{style: weight}` dict.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np

from models.interface import FrameBatch, State, StreamingModel, split_state, stack_states, upgrade_state, weight_vector

from .metrics import Metrics

T = TypeVar("T")


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
    frames = FrameBatch(
        np.stack([r.root for r in requests]), np.stack([r.rotations for r in requests]), control=control
    )
    names = model.styles()
    out, new_state = model.step_batch(state, frames, np.stack([weight_vector(names, r.weights) for r in requests]))
    states = split_state(new_state)
    return [(out.root[i], out.rotations[i], states[i]) for i in range(len(requests))]


class ModelThread:
    """The one worker thread for model steps and style changes, and whether work is on it.

    Style changes (`run`) are counted from submission until the thread has finished them, so
    `idle` is false for as long as one might still touch a model."""

    def __init__(self) -> None:
        self.executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="model-step")
        self._busy = 0

    @property
    def idle(self) -> bool:
        return self._busy == 0

    async def run(self, fn: Callable[..., T], *args: Any) -> T:
        """`fn(*args)` on the thread; the event loop is free meanwhile."""
        loop = asyncio.get_running_loop()
        self._busy += 1
        job = self.executor.submit(fn, *args)
        job.add_done_callback(lambda _: loop.call_soon_threadsafe(self._done))
        return await asyncio.wrap_future(job)

    def _done(self) -> None:
        self._busy -= 1

    def shutdown(self) -> None:
        self.executor.shutdown(wait=False, cancel_futures=True)


class Batcher:
    def __init__(
        self,
        model: StreamingModel,
        thread: ModelThread,
        metrics: Metrics,
        wait_s: float = 0.001,
        max_batch: int = 256,
        enabled: bool = True,
        open_sessions: Callable[[], int] | None = None,
        inline_max_s: float = 0.005,
    ) -> None:
        self.model, self.thread = model, thread
        self.metrics = metrics.model(model.name)
        self.wait_s, self.max_batch = wait_s, (max_batch if enabled else 1)
        # a batch is full once every open session of this model is in it: waiting longer gains nothing
        self.open_sessions = open_sessions or (lambda: self.max_batch)
        self.inline_max_s = inline_max_s
        # measured step seconds by batch size class (bit length of the size), smoothed: a step has
        # a large fixed part (LTI: ~1.2 ms at 1 session, ~5 ms at 256), so no per-session rate fits
        self.step_s: dict[int, float] = {}
        self._pending: list[StepRequest] = []
        self._want = 1  # requests pending that wake the gathering batcher
        self._arrived = asyncio.Event()
        self._task: asyncio.Task | None = None

    def start(self) -> None:
        self._task = asyncio.get_running_loop().create_task(self._run(), name=f"batcher-{self.model.name}")

    async def stop(self) -> None:
        if self._task:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)

    async def step(
        self,
        state: State,
        root: np.ndarray,
        rotations: np.ndarray,
        weights: dict[str, float],
        control: np.ndarray | None = None,
    ):
        future = asyncio.get_running_loop().create_future()
        self._pending.append(StepRequest(state, root, rotations, weights, future, control))
        if len(self._pending) >= self._want:
            self._arrived.set()
        return await future

    async def _wait_for(self, count: int) -> None:
        """Until `count` requests are pending (no timeout: the caller bounds it)."""
        while len(self._pending) < count:
            self._want = count
            self._arrived.clear()
            await self._arrived.wait()

    async def _gather(self) -> list[StepRequest]:
        await self._wait_for(1)
        full = min(self.max_batch, max(1, self.open_sessions()))
        if len(self._pending) < full and self.wait_s > 0:
            try:
                async with asyncio.timeout(self.wait_s):
                    await self._wait_for(full)
            except TimeoutError:
                pass
        self._want = 1
        batch, self._pending = self._pending[: self.max_batch], self._pending[self.max_batch :]
        return batch

    def _inline(self, size: int) -> bool:
        return self.thread.idle and self.step_s.get(size.bit_length(), 0.0) <= self.inline_max_s

    async def _run(self) -> None:
        while True:
            batch = await self._gather()
            t0 = time.perf_counter()
            try:
                if self._inline(len(batch)):
                    results = run_step(self.model, batch)
                else:
                    results = await asyncio.get_running_loop().run_in_executor(
                        self.thread.executor, run_step, self.model, batch
                    )
            except Exception as exc:  # a model failure fails this batch's frames, never the batcher
                for req in batch:
                    if not req.future.done():
                        req.future.set_exception(exc)
                continue
            seconds = time.perf_counter() - t0
            size_class = len(batch).bit_length()
            self.step_s[size_class] = self.step_s.get(size_class, seconds) * 0.8 + 0.2 * seconds
            self.metrics.step_latency.observe(seconds)
            self.metrics.batch_size.observe(len(batch))
            for req, result in zip(batch, results):
                if not req.future.done():
                    req.future.set_result(result)
