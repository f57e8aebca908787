"""Rig builds run off the event loop, one at a time per caller (`service.rig_builds`): a caller's
second new rig waits for its first, another caller's does not, and the loop keeps running
while they build."""

from __future__ import annotations

import asyncio
import threading
from pathlib import Path

from models.motion.assets import bandai_namco_skeleton
from service.rig_builds import RigBuilds

from .test_rig_limits import with_offsets

# a rig of this test's own (no other test builds it first): the mixamo fixture, spine moved
RIG = with_offsets((Path(__file__).parent / "fixtures" / "rigs" / "mixamo.bvh").read_text(), r"Spine$", "0 10.123 0")


def test_one_callers_builds_queue_behind_each_other_not_in_front_of_anothers():
    release = {name: threading.Event() for name in ("a1", "a2", "b1")}
    started: list[str] = []

    def build(name: str) -> str:
        started.append(name)
        assert release[name].wait(30), name
        return name

    async def scenario() -> None:
        builds = RigBuilds(per_caller=1)
        a1 = asyncio.create_task(builds.run("a", build, "a1"))
        a2 = asyncio.create_task(builds.run("a", build, "a2"))
        b1 = asyncio.create_task(builds.run("b", build, "b1"))
        while sorted(started) != ["a1", "b1"]:  # a2 waits for a1; b1 does not wait for a
            await asyncio.sleep(0.01)  # the loop runs while builds hold their threads
        assert "a2" not in started
        release["b1"].set()
        assert await b1 == "b1" and "a2" not in started
        release["a1"].set()
        release["a2"].set()
        assert (await a1, await a2) == ("a1", "a2")
        assert not builds._gates  # a caller's gate goes with its last build

    asyncio.run(scenario())


def test_a_rig_seen_before_is_answered_without_a_thread():
    async def scenario() -> None:
        builds = RigBuilds()
        bn = bandai_namco_skeleton()
        first = await builds.adapter("a", None, RIG, bn)
        assert builds.built == 1
        assert await builds.adapter("b", None, RIG, bn) is first and builds.built == 1

    asyncio.run(scenario())
