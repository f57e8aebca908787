"""Rig builds run in child processes, one at a time per caller (`service.rig_builds`): a caller's
second new rig waits for its first, another caller's does not, the loop keeps running while they
build, and a child that dies or hangs fails its build with a typed error, never a hang."""

from __future__ import annotations

import asyncio
import operator
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from models.motion.assets import bandai_namco_skeleton
from service import protocol as P
from service.background import in_background
from service.rig_builds import RigBuilds, RigWorkers, WorkerFailed

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
        builds = RigBuilds(per_caller=1, runner=in_background)  # threads: the test's builds wait on its events
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
        # the same rig spelled otherwise is built (parsed) in the child, and answered with the first adapter
        respelled = RIG.replace("OFFSET ", "OFFSET  ")
        assert await builds.adapter("b", None, respelled, bn) is first and builds.built == 2
        builds.close()

    asyncio.run(scenario())


def test_a_rig_refused_before_is_refused_again_without_a_thread():
    """The same bad rig sent again (a start, a join, over and over) is not parsed again: its
    typed error comes from the dict, each time a copy of its own."""
    bad = with_offsets(RIG, r"Spine$", "1e308 0 0")

    async def scenario() -> list[P.ProtocolError]:
        builds = RigBuilds()
        bn = bandai_namco_skeleton()
        errors = []
        for caller in ("a", "a", "b"):
            try:
                await builds.adapter(caller, None, bad, bn)
            except P.ProtocolError as err:
                errors.append(err)
        assert builds.built == 1
        builds.close()
        return errors

    errors = asyncio.run(scenario())
    assert [e.code for e in errors] == ["bad_skeleton"] * 3 and "not finite" in errors[0].message
    assert len({id(e) for e in errors}) == 3 and len({e.message for e in errors}) == 1


def test_a_child_that_dies_fails_its_build_with_a_typed_error_and_the_next_build_gets_a_new_one():
    async def scenario() -> None:
        workers = RigWorkers(processes=1)
        try:
            try:
                await workers.run(os._exit, 3)
                raise AssertionError("a dead child answered")
            except WorkerFailed as err:
                assert (err.code, err.fatal, err.close_code) == ("internal", True, 1011) and "died" in err.message
            assert await workers.run(operator.add, 1, 2) == 3 and workers.failures == 1
        finally:
            workers.close()

    asyncio.run(scenario())


def test_a_child_that_does_not_answer_is_killed_and_its_build_fails_typed():
    async def scenario() -> None:
        workers = RigWorkers(processes=1, timeout_s=0.5)
        try:
            try:
                await workers.run(time.sleep, 600)
                raise AssertionError("a hung child answered")
            except WorkerFailed as err:
                assert err.code == "internal" and "no answer" in err.message
            workers.timeout_s = 60.0
            assert await workers.run(operator.mul, 6, 7) == 42 and workers.failures == 1
        finally:
            workers.close()

    asyncio.run(scenario())


SERVER = """
import asyncio, os, sys, time
from service.rig_builds import RigWorkers
workers = RigWorkers(processes=1)
print(asyncio.run(workers.run(os.getpid)), flush=True)
time.sleep(600)
"""


def _gone(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/status").read_text().split("State:")[1].split()[0] in ("Z", "X")
    except (FileNotFoundError, ProcessLookupError):
        return True


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads /proc")
def test_a_child_ends_when_its_server_is_killed():
    """A server killed outright never stops its executor: its children must not outlive it."""
    server = subprocess.Popen([sys.executable, "-c", SERVER], stdout=subprocess.PIPE, text=True)
    try:
        child = int(server.stdout.readline())  # type: ignore[union-attr]
        assert not _gone(child)
    finally:
        server.kill()
        server.wait()
    deadline = time.monotonic() + 60
    while not _gone(child):
        assert time.monotonic() < deadline, f"child {child} outlived its server"
        time.sleep(0.1)
