"""Bulk work on the event loop, paced: slices of about `slice_s`, each followed by a pause three
times as long as the slice ran.

A crowd's ticks, its large joins, its periodic snapshots, a large leave and its close are
thousands of small steps of Python and model parts. Run back to back they held every other
connection's frames: yielding with `sleep(0)` between parts is not enough, since it lets the loop
run one pass while a session's frame needs several (read, queue, batch, step, send), each of
which then waits behind the next part; and a loop thread that never sleeps loses the scheduler's
favour on a busy machine, so a neighbour's frame also waits for the CPU. Pausing for a multiple of
what the slice ran keeps one crowd to about a quarter of the loop's time while others want it, and
the crowd's own client pays the wait. (`clients.hostile_bench`'s crowd fill, 712-character ticks,
neighbour p99 / quiet p99 in three alternating pairs on the shared 2-core machine: pause = slice
2.38, 2.24, 2.31; pause = 3x slice 1.57, 2.00, 1.72, the crowd answering 24-29 ticks in 6 s
instead of 36-54.)
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

SLICE_S = 0.001  # about one batch of a crowd part: what a neighbour's frame may wait behind
PAUSE_PER_SLICE = 3.0  # pause / slice: one crowd takes at most ~1/4 of the loop while paced
MAX_PAUSE_S = 0.02  # a slice the OS preempted for long is not made up for in full


class Pacer:
    """Call `pace()` between units of bulk work; once a slice has run `slice_s` it pauses."""

    def __init__(self, slice_s: float = SLICE_S) -> None:
        self.slice_s = slice_s
        self.pauses = 0
        self._since = time.perf_counter()

    async def pace(self) -> None:
        ran = time.perf_counter() - self._since
        if ran >= self.slice_s:
            self.pauses += 1
            await asyncio.sleep(min(PAUSE_PER_SLICE * ran, MAX_PAUSE_S))
            self._since = time.perf_counter()


class LoopShare:
    """One connection's share of the event loop for handling its messages: what handling them
    took is spent from a budget that refills at `share` of the wall clock, up to `burst_s`; once
    it is spent, the connection's receiver pauses until the budget is back. A client sending at
    any real-time rate (a frame takes ~0.1 ms to handle) never waits; a flood of messages gets
    `share` of the loop (as `Pacer` gives a crowd), and the rest waits in its own socket buffers
    (the transport stops reading: the flooder's sends block) instead of in front of every other
    connection's frames."""

    def __init__(
        self,
        share: float = 1.0 / (1.0 + PAUSE_PER_SLICE),
        burst_s: float = 4 * SLICE_S,
        clock: Callable[[], float] = time.perf_counter,
    ) -> None:
        self.share, self.burst_s, self.clock = share, burst_s, clock
        self.left = burst_s
        self.at = clock()
        self.pauses = 0

    @property
    def limited(self) -> bool:
        return 0.0 < self.share < 1.0

    def charge(self, seconds: float) -> None:
        """Spend `seconds` of handling (the connection's other task: its replies) without pausing
        here: the receiver pauses for it at its next message."""
        now = self.clock()
        self.left = min(self.burst_s, self.left + (now - self.at) * self.share) - seconds
        self.at = now

    async def spend(self, seconds: float) -> None:
        """Spend `seconds` of the receiver's handling, and pause while the budget is spent."""
        self.charge(seconds)
        if self.left < 0 and self.limited:
            self.pauses += 1
            await asyncio.sleep(min(-self.left / self.share, MAX_PAUSE_S))
            self.charge(0.0)  # what the pause refilled
