"""Rig builds run in child processes, one at a time per caller (`service.rig_builds`): a caller's
second new rig waits for its first, another caller's does not, the loop keeps running while they
build, and a child that dies or hangs fails its build with a typed error, never a hang."""

from __future__ import annotations

import asyncio
import operator
import os
import signal
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


IDLE_CHILD = """
import os
from service.background import background_placement
from service.rig_builds import _child_start
_child_start(background_placement(), idle=True)
print(os.sched_getscheduler(0) == os.SCHED_IDLE)
"""


@pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="Linux scheduling classes")
def test_an_idle_child_runs_only_on_a_cpu_with_nothing_else_to_do():
    """So a build takes no CPU time from a streaming thread."""
    assert (
        subprocess.run([sys.executable, "-c", IDLE_CHILD], capture_output=True, text=True, check=True).stdout
        == "True\n"
    )


@pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="Linux scheduling classes")
def test_a_build_its_idle_child_never_runs_is_answered_by_a_normal_one_and_the_next_goes_there_at_once():
    """On a machine never idle, an idle child would never run: past `idle_wait_s` the same call
    goes to a child at the background's niceness (here the idle child is stopped outright), and
    the builds right after skip the idle children."""

    async def scenario() -> None:
        answers: list[bool] = []
        workers = RigWorkers(processes=1, idle_wait_s=0.2, answered=answers.append)
        idle_pool = workers._executor(idle=True)
        idle_pool.submit(int)  # starts its child
        stopped = list(idle_pool._processes)
        for pid in stopped:
            os.kill(pid, signal.SIGSTOP)
        try:
            assert await workers.run(os.sched_getscheduler, 0) != os.SCHED_IDLE and workers.promoted == 1
            assert await workers.run(operator.add, 2, 3) == 5 and workers.promoted == 1  # not sent to the idle child
            assert answers == [False, False]  # what /metrics counts as `normal`
            assert False in workers._pools  # kept while the idle children starve
        finally:
            for pid in stopped:
                os.kill(pid, signal.SIGCONT)
            workers.close()

    asyncio.run(scenario())


def test_the_normal_children_go_once_an_idle_one_answers_again():
    """They are only the fallback for a starved idle child: kept, they would hold their memory
    (120-250 MB each) for good."""

    async def scenario() -> None:
        workers = RigWorkers(processes=1, idle_wait_s=30.0)
        workers._executor(idle=False).submit(int).result()
        try:
            assert await workers.run(operator.add, 1, 2) == 3 and workers.promoted == 0
            assert False not in workers._pools and True in workers._pools
        finally:
            workers.close()

    asyncio.run(scenario())
