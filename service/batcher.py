"""Cross-session batching: frames of many sessions run as one `step_batch` call.

A request is one session's frame, or all of one crowd connection's characters of the model
(`service.crowd`): rows that go into the batch together and come back as slices. Each
connection has at most one request in flight (its processor awaits the reply before taking the
next), so a batch never holds two frames of one character. The batcher waits at most `wait_s`
after the first request for others to join, or until every open session of the model has one
in, then runs the step and scatters the results back (one future per request, nothing else per
request or row: no queue, no task, no timer).

The wait counts sessions only, never crowds. A crowd's part is already a batch of its own, and
it comes when its client ticks and its pacer lets it (`service.pacing`), not every frame period:
counted as one more request to wait for, an idle or paced crowd made every session's frame wait
the whole `wait_s` for nothing. (hostile_bench's `crowd rigs`, a crowd of one idle character
beside 45-rig joins, on the loaded shared 2-core machine: the neighbour's server-side time per
frame, median, 2.31-2.73 ms with the crowd counted, 1.07-1.25 ms without; its round-trip median
3.1-4.2 ms against 1.8-2.0 ms.) And sessions' frames go first: when a batch forms, the pending
sessions' frames make it alone, and a crowd's part waits for the next one. In one batch with a
part, a session's frame waited for the part's many rows (a 64-row LTI part is 2-6 ms on the
loaded machine, a frame alone ~1 ms); a crowd's part waits at most one session step.

Where the step runs: model steps and style changes share one worker thread (`ModelThread`), so
a style change never runs in the middle of a step. A step predicted to take less than
`inline_max_s` runs right on the event loop when that thread is idle: the compiled step kernels
hold the GIL, so handing a short step to the thread only adds two thread switches and a wait for
the GIL; a long one goes to the thread, which lets the event loop in between kernels. A batch with
a crowd's part in it always goes to the thread, however short: a 64-row part is 2-6 ms of LTI
step on the loaded 2-core machine, and on the loop every connection waited for all of it, ~12 %
of a neighbour's frames batched into it too (hostile_bench's crowd fill, 712-character ticks,
two alternating pairs of two rounds on the loaded machine: the neighbour's round-trip median
2.6-3.4 ms inline, 1.9-2.2 ms on the thread, 1.6-2.0 ms in the quiet periods; the crowd answered
19-28 ticks in 6 s instead of 27-32: it pays for the thread hops). (Compiling
the kernels with `nogil=True`, so the loop could run beside them, was measured worse on the 2-core
machine: Style-ERD crowds of 10 x 100, alternated with the kernels holding the GIL, p99 16.4-20.6
against 15.6-17.8 ms: the loop, the step's Python glue and the load test's clients then fight for
the same two cores and the GIL hands over more often.)

The model's style set may change between steps, so the step first brings every session's state
to the current style set (`upgrade_state`) and builds the weight vectors over the current
`styles()` from each session's `{style: weight}` dict (a crowd's weight rows are remapped by
style name).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np

from models.interface import (
    FrameBatch,
    State,
    StreamingModel,
    stack_states,
    upgrade_state,
    weight_columns,
    weight_vector,
)

from .metrics import Metrics

T = TypeVar("T")
PART_ROWS_START = 8  # a crowd's part before any step of the model was measured (`Batcher.part_rows`)


@dataclass
class StepRequest:
    """Rows to step together: one session's frame (one row), or one crowd's characters of this
    model (many rows, `service.crowd`), kept together through the step and back."""

    state: State  # every entry with the rows first
    root: np.ndarray  # (n, 3)
    rotations: np.ndarray  # (n, J, 4)
    weights: dict[str, float] | np.ndarray  # one session's {style: weight}, or (n, S) over `names`
    future: asyncio.Future
    control: np.ndarray | None = None  # (n, 5) controller ticks, see `FrameBatch.control`
    names: list[str] | None = None  # the styles the columns of an array `weights` stand for

    @property
    def rows(self) -> int:
        return len(self.root)

    @property
    def session_frame(self) -> bool:
        """One session's frame (its weights a dict), not a crowd's part."""
        return isinstance(self.weights, dict)

    def weights_over(self, names: list[str]) -> np.ndarray:
        """(n, len(names)) weights over the model's styles at step time: a style deleted since the
        request was made drops out (its share passes the input through), one added weighs 0."""
        if isinstance(self.weights, dict):
            return weight_vector(names, self.weights)[None]
        if self.names == names:
            return self.weights
        return weight_columns(self.weights, self.names or [], names)


StepResult = tuple[np.ndarray, np.ndarray, State]  # root (n, 3), rotations (n, J, 4), state (n rows)


def run_step(model: StreamingModel, requests: list[StepRequest]) -> list[StepResult]:
    """One batched step over the requests' rows; pure, runs on the worker thread. Each request
    gets its rows back as slices of the batch's arrays (states are never modified in place)."""
    names = model.styles()
    states = [upgrade_state(model, r.state) for r in requests]
    state = states[0] if len(states) == 1 else stack_states(states)
    control = None
    if any(r.control is not None for r in requests):  # rows without control: flag 0, follow the input frames
        control = np.concatenate([r.control if r.control is not None else np.zeros((r.rows, 5)) for r in requests])
    if len(requests) == 1:
        root, rotations, weights = requests[0].root, requests[0].rotations, requests[0].weights_over(names)
    else:
        root = np.concatenate([r.root for r in requests])
        rotations = np.concatenate([r.rotations for r in requests])
        weights = np.concatenate([r.weights_over(names) for r in requests])
    out, new_state = model.step_batch(state, FrameBatch(root, rotations, control=control), weights)
    results, start = [], 0
    for r in requests:
        rows = slice(start, start + r.rows)
        results.append((out.root[rows], out.rotations[rows], {key: value[rows] for key, value in new_state.items()}))
        start += r.rows
    return results


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
        self._pending_rows = 0
        self._want = 1  # requests pending that wake the gathering batcher
        self._arrived = asyncio.Event()
        self._task: asyncio.Task | None = None
        self._loop: asyncio.AbstractEventLoop | None = None

    @property
    def loop(self) -> asyncio.AbstractEventLoop:
        """The event loop, looked up once: `asyncio.get_running_loop` makes a getpid() system call
        on every call (3 % of a loaded server's busy time when it ran once per frame, py-spy --native)."""
        if self._loop is None:
            self._loop = asyncio.get_running_loop()
        return self._loop

    def start(self) -> None:
        self._task = self.loop.create_task(self._run(), name=f"batcher-{self.model.name}")

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
    ) -> tuple[np.ndarray, np.ndarray, State]:
        """One session's frame: root (3,), rotations (J, 4), its {style: weight}; returns its
        output root and rotations and its new (one-row) state."""
        out_root, out_rot, new_state = await self.step_rows(
            state, root[None], rotations[None], weights, None if control is None else control[None]
        )
        return out_root[0], out_rot[0], new_state

    def step_rows(
        self,
        state: State,
        root: np.ndarray,
        rotations: np.ndarray,
        weights: dict[str, float] | np.ndarray,
        control: np.ndarray | None = None,
        names: list[str] | None = None,
    ) -> asyncio.Future[StepResult]:
        """Rows stepped in one batch with every other request waiting: (n, 3) roots, (n, J, 4)
        rotations, an (n, S) weight array over `names` (or one row's dict); the future gives
        their outputs and new state, rows in the same order."""
        future: asyncio.Future[StepResult] = self.loop.create_future()
        self._pending.append(StepRequest(state, root, rotations, weights, future, control, names))
        self._pending_rows += len(root)
        if len(self._pending) >= self._want:
            self._arrived.set()
        return future

    async def _wait_for(self, count: int, seconds: float | None = None) -> None:
        """Until `count` requests are pending, or `seconds` have passed. A timer that sets the
        event, not `asyncio.timeout`: nearly every batch of spread sessions waits out its
        `wait_s`, and a timeout ends the wait by raising through the coroutines."""
        expired = False

        def expire() -> None:
            nonlocal expired
            expired = True
            self._arrived.set()

        timer = None if seconds is None else self.loop.call_later(seconds, expire)
        try:
            while len(self._pending) < count and not expired:
                self._want = count
                self._arrived.clear()
                await self._arrived.wait()
        finally:
            if timer is not None:
                timer.cancel()

    async def _gather(self) -> list[StepRequest]:
        await self._wait_for(1)
        full = min(self.max_batch, max(1, self.open_sessions()))
        if len(self._pending) < full and self._pending_rows < self.max_batch and self.wait_s > 0:
            await self._wait_for(full, self.wait_s)
        self._want = 1
        # sessions' frames first (module doc); whole requests up to `max_batch` rows (a crowd's
        # rows stay together; at least one request)
        frames = [r for r in self._pending if r.session_frame]
        batch: list[StepRequest] = []
        rows = 0
        for request in frames or self._pending:
            if batch and rows + request.rows > self.max_batch:
                break
            batch.append(request)
            rows += request.rows
        taken = {id(r) for r in batch}
        self._pending = [r for r in self._pending if id(r) not in taken]
        self._pending_rows -= rows
        return batch

    def part_rows(self, seconds: float) -> int:
        """The most rows of a crowd's request that step within `seconds`, from the measured step
        times: a session's frame that comes while a part steps waits for all of it, holding the
        GIL in compiled kernels (LTI: 64 rows 1-2 ms; Style-ERD 64 rows ~10 ms on the loaded 2-core
        machine). A size class whose step took at most half of `seconds` lets the next one be tried
        (twice the rows take at most twice the time: a step's cost is sublinear in its rows)."""
        rows = PART_ROWS_START
        for size_class, took in self.step_s.items():
            if took <= seconds:
                top = 2**size_class - 1
                rows = max(rows, 2 * top + 1 if took <= seconds / 2 else top)
        return min(rows, self.max_batch)

    def _inline(self, batch: list[StepRequest]) -> bool:
        """Step `batch` on the event loop: only sessions' frames (one row each; a crowd's part
        always goes to the thread, module doc), the thread idle, the step predicted short."""
        if any(r.rows > 1 for r in batch) or not self.thread.idle:
            return False
        return self.step_s.get(len(batch).bit_length(), 0.0) <= self.inline_max_s

    async def _run(self) -> None:
        while True:
            batch = await self._gather()
            t0 = time.perf_counter()
            try:
                if self._inline(batch):
                    results = run_step(self.model, batch)
                else:
                    results = await self.loop.run_in_executor(self.thread.executor, run_step, self.model, batch)
            except Exception as exc:  # a model failure fails this batch's frames, never the batcher
                for req in batch:
                    if not req.future.done():
                        req.future.set_exception(exc)
                continue
            seconds = time.perf_counter() - t0
            size_class = sum(r.rows for r in batch).bit_length()
            self.step_s[size_class] = self.step_s.get(size_class, seconds) * 0.8 + 0.2 * seconds
            self.metrics.step_latency.observe(seconds)
            self.metrics.batch_size.observe(sum(r.rows for r in batch))
            for req, result in zip(batch, results):
                if not req.future.done():
                    req.future.set_result(result)
