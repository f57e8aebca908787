"""A connection's share of the event loop (`service.pacing.LoopShare`), on a simulated clock: a
real-time stream never pauses, a flood is held to its share, and 0 turns the limit off."""

from __future__ import annotations

import asyncio

import pytest

from service import pacing
from service.pacing import LoopShare


class Clock:
    """Time that moves only when told: by handling, or by a pause (`asyncio.sleep` patched)."""

    def __init__(self) -> None:
        self.now = 0.0
        self.slept = 0.0

    def __call__(self) -> float:
        return self.now

    async def sleep(self, seconds: float) -> None:
        self.now += seconds
        self.slept += seconds


@pytest.fixture
def clock(monkeypatch) -> Clock:
    c = Clock()
    monkeypatch.setattr(pacing.asyncio, "sleep", c.sleep)
    return c


def run(share: LoopShare, clock: Clock, messages: int, handling_s: float, gap_s: float) -> None:
    async def receiver() -> None:
        for _ in range(messages):
            clock.now += gap_s  # waiting for the next message
            clock.now += handling_s
            await share.spend(handling_s)

    asyncio.run(receiver())


def test_a_real_time_stream_never_pauses(clock):
    share = LoopShare(0.25, clock=clock)
    run(share, clock, 600, handling_s=0.0002, gap_s=1 / 120)  # 120 fps at twice a frame's usual cost
    assert share.pauses == 0 and clock.slept == 0.0


def test_a_flood_gets_its_share_of_the_loop_and_no_more(clock):
    share = LoopShare(0.25, burst_s=0.004, clock=clock)
    handling = 10_000 * 0.0001
    run(share, clock, 10_000, handling_s=0.0001, gap_s=0.0)
    assert share.pauses > 0
    assert handling / clock.now == pytest.approx(0.25, rel=0.01)  # the burst is all it gets beyond its share


def test_what_the_connection_spends_answering_counts_too(clock):
    share = LoopShare(0.25, burst_s=0.004, clock=clock)
    share.charge(0.005)  # its replies took 5 ms of the loop
    run(share, clock, 1, handling_s=0.0001, gap_s=0.0)
    deficit = 0.005 + 0.0001 - 0.004 - 0.25 * 0.0001  # spent, less the burst and what its handling refilled
    assert clock.slept == pytest.approx(deficit / 0.25, rel=0.01)  # paid back at its share


@pytest.mark.parametrize("off", [0.0, 1.0])
def test_no_limit_at_zero_or_one(clock, off):
    share = LoopShare(off, clock=clock)
    run(share, clock, 1000, handling_s=0.001, gap_s=0.0)
    assert share.pauses == 0 and clock.slept == 0.0
