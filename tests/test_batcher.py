"""Where the batcher runs a step (`service.batcher`): sessions' frames on the event loop while
the model thread is idle, a batch with a crowd's part always on the model thread."""

from __future__ import annotations

import asyncio
import threading
from types import SimpleNamespace

import numpy as np

from service import batcher as batcher_module
from service.batcher import Batcher, ModelThread
from service.metrics import Metrics


def test_a_crowd_part_is_stepped_on_the_model_thread_and_a_frame_on_the_loop(monkeypatch):
    """A crowd's part on the event loop held every connection for its whole step (2-6 ms of LTI
    for 64 rows); a session's frame stays on the loop (a thread hop costs it more than its step)."""
    ran: list[tuple[list[int], bool]] = []

    def run_step(model, requests):  # noqa: ANN001, ANN202 - `batcher.run_step`'s shape, no model
        ran.append(([r.rows for r in requests], threading.current_thread() is threading.main_thread()))
        return [(np.zeros((r.rows, 3)), np.zeros((r.rows, 1, 4)), {}) for r in requests]

    monkeypatch.setattr(batcher_module, "run_step", run_step)

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
