"""Where and with what the batcher runs a step (`service.batcher`): sessions' frames on the
event loop while the model thread is idle, a batch with a crowd's part always on the model
thread, and sessions' frames never in one batch with a crowd's part."""

from __future__ import annotations

import asyncio
import threading
from types import SimpleNamespace

import numpy as np

from service import batcher as batcher_module
from service.batcher import Batcher, ModelThread
from service.metrics import Metrics


def _record_steps(monkeypatch) -> list[tuple[list[int], bool]]:  # noqa: ANN001
    """Each step's request sizes and whether it ran on the event loop's thread (no model)."""
    ran: list[tuple[list[int], bool]] = []

    def run_step(model, requests):  # noqa: ANN001, ANN202 - `batcher.run_step`'s shape
        ran.append(([r.rows for r in requests], threading.current_thread() is threading.main_thread()))
        return [(np.zeros((r.rows, 3)), np.zeros((r.rows, 1, 4)), {}) for r in requests]

    monkeypatch.setattr(batcher_module, "run_step", run_step)
    return ran


def test_a_crowd_part_is_stepped_on_the_model_thread_and_a_frame_on_the_loop(monkeypatch):
    """A crowd's part on the event loop held every connection for its whole step (2-6 ms of LTI
    for 64 rows); a session's frame stays on the loop (a thread hop costs it more than its step)."""
    ran = _record_steps(monkeypatch)

    async def main() -> None:
        thread = ModelThread()
        batcher = Batcher(SimpleNamespace(name="m"), thread, Metrics(), wait_s=0.0)
        batcher.start()
        try:
            for rows in (1, 64, 1, 2):
                await batcher.step_rows({}, np.zeros((rows, 3)), np.zeros((rows, 1, 4)), {"a": 1.0})
        finally:
            await batcher.stop()
            thread.shutdown()

    asyncio.run(main())
    assert ran == [([1], True), ([64], False), ([1], True), ([2], False)]


def test_sessions_frames_are_stepped_before_a_pending_crowd_part_and_apart_from_it(monkeypatch):
    """In one batch with a crowd's part, a session's frame waited for all the part's rows."""
    ran = _record_steps(monkeypatch)

    async def main() -> None:
        thread = ModelThread()
        batcher = Batcher(SimpleNamespace(name="m"), thread, Metrics(), wait_s=0.0)
        part = batcher.step_rows({}, np.zeros((64, 3)), np.zeros((64, 1, 4)), np.ones((64, 1)), names=["a"])
        frames = [batcher.step_rows({}, np.zeros((1, 3)), np.zeros((1, 1, 4)), {"a": 1.0}) for _ in range(2)]
        batcher.start()
        try:
            await asyncio.gather(part, *frames)
        finally:
            await batcher.stop()
            thread.shutdown()

    asyncio.run(main())
    assert ran == [([1, 1], True), ([64], False)]


def test_a_crowd_part_holds_as_many_rows_as_step_within_the_slice():
    """Parts sized by the model's measured step times: a slow model's parts are small, a fast
    one's grow by doubling while a size class steps in half the slice."""
    batcher = Batcher(SimpleNamespace(name="m"), ModelThread(), Metrics(), max_batch=256)
    assert batcher.part_rows(0.001) == batcher_module.PART_ROWS_START  # nothing measured yet
    batcher.step_s = {1: 0.0002, 4: 0.0009, 6: 0.004}  # 1 row, 8-15 rows, 32-63 rows
    assert batcher.part_rows(0.001) == 15
    batcher.step_s[4] = 0.0004  # 8-15 rows in under half the slice: try 16-31
    assert batcher.part_rows(0.001) == 31
    batcher.step_s = {9: 0.0001}
    assert batcher.part_rows(0.001) == 256  # never more than a batch
