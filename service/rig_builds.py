"""Rigs built in a child process, a few at a time per caller.

Parsing a client's BVH header and setting up its retargeter takes 10-30 ms for a CMU rig and
~170 ms for a large one, in a session's `start`, a crowd's `join` or a `POST /v1/skeletons`. On
the event loop every other stream waited (45 new rigs per join: the neighbour's p99 x92); on a
background thread it still held the GIL, handing it to the loop only at the switch interval, so
a neighbour's round trip, which needs the GIL several times, took 2-3x its quiet p99 whenever
new rigs were built (hostile_bench `crowd rigs`, `big rigs`). So the build runs in a child
process (`RigWorkers`: forked from the server's fork server, kept for the next build, on the
background's CPUs), and the loop only unpickles the built adapter (~30 kB, ~0.2 ms).

The children run at `SCHED_IDLE`: at nice 10 a build still took the CPU the event loop was
waiting for often enough to double a neighbour's p99 (crowd rigs: run-queue wait p99 2.0 ms vs
0.3 ms quiet). An idle child runs only on a CPU with nothing else runnable, so on a machine that
is never idle it would never run, and an unprivileged process cannot leave `SCHED_IDLE` again: a
call an idle child has not answered within IDLE_WAIT_S is also sent to a child at the
background's niceness (the first answer wins), and the calls of the next IDLE_BACKOFF_S go there
straight away, so a busy machine pays that wait once per back-off, not once per rig. Those
normal children go again once an idle one answers after the back-off.

Each caller (`Principal.key`) has at most PER_CALLER builds running; its further ones wait their
turn on its own gate, so one tenant's stream of new rigs queues behind itself, not in front of
anyone else's. A rig seen before costs one dict lookup (`skeletons.cached_adapter`), a rig of
the same content in another spelling gets the adapter built for the first (`skeletons.adopt`),
and a rig refused before is refused from a dict by a digest of the request's text, so a client
sending the same bad rig again and again is not sent to the child each time.

A child that dies (killed, out of memory) or does not answer within the time limit (it is then
killed) fails only the builds it held, with a typed `internal` error (`WorkerFailed`); the next
build starts a fresh child.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import json
import multiprocessing
import os
import signal
import threading
import time
from collections import Counter, OrderedDict
from collections.abc import Awaitable, Callable
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any, TypeVar

from models.motion.humanoid import RigError
from models.motion.skeleton import Skeleton

from . import protocol as P
from .background import Placement, background_placement, enter_background, in_background
from .skeletons import SkeletonAdapter, adapter_for, adopt, cached_adapter

PER_CALLER = 1  # one caller's rig builds at once
PROCESSES = 2  # children for every caller's builds together
IDLE_WAIT_S = 0.5  # a build an idle child has not answered by then runs at the background's niceness too
IDLE_BACKOFF_S = 5.0  # after which the builds that follow skip the idle children for this long
TIMEOUT_S = 30.0  # a build capped by `rig_check` takes well under a second; a child silent this long is killed
REFUSED_KEPT = 256  # typed refusals remembered (digests: a 200 kB header costs 16 bytes here)
WATCH_S = 1.0  # how often a child looks for the server (`_exit_with`)
CLOSE_INTERNAL = 1011
T = TypeVar("T")
Runner = Callable[..., Awaitable[Any]]


class WorkerFailed(P.ProtocolError):
    """The build's child process died or hung: the server's fault, not the rig's (never kept as a
    refusal); fatal for a session's `start` (close 1011: connect again), one character's error in
    a `join`, 503 from `POST /v1/skeletons`."""

    def __init__(self, why: str) -> None:
        super().__init__(
            "internal", f"the rig could not be built ({why}); try again", fatal=True, close_code=CLOSE_INTERNAL
        )


# ---- the child ---------------------------------------------------------------------------------


def _child_start(where: Placement, server: int | None = None, idle: bool = False) -> None:
    """A child's start: the background's priority and CPUs (the streams' core stays theirs), or
    `SCHED_IDLE` (runs only when a CPU has nothing else to run), and a watch on the server
    (`_exit_with`)."""
    enter_background(where)
    if idle:
        with contextlib.suppress(OSError, AttributeError):  # not Linux
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    if server is not None:
        threading.Thread(target=_exit_with, args=(server,), name="server-watch", daemon=True).start()


def _exit_with(server: int) -> None:
    """End this child once the server process is gone. A child the executor did not stop (the
    server killed, or exiting before its executor's thread ran) waits on its call queue for ever,
    and holds the fork server open with it: without this, every such server left both behind."""
    while True:
        time.sleep(WATCH_S)
        try:
            os.kill(server, 0)
        except ProcessLookupError:
            os._exit(0)
        except PermissionError:  # another user's process now has its id: the server is gone too
            os._exit(0)


def _call(fn: Callable[..., Any], args: tuple, kwargs: dict) -> tuple[str, Any]:
    """`fn(*args, **kwargs)` in the child, its typed errors as plain tuples: `ProtocolError` and
    `RigError` take more than a message, which pickling an exception does not carry."""
    try:
        return "ok", fn(*args, **kwargs)
    except P.ProtocolError as err:
        return "protocol", (err.code, err.message, err.seq, err.fatal, err.close_code, err.character)
    except RigError as err:
        return "rig", (err.code, err.message, err.missing)


def _answer(status: str, payload: Any) -> Any:
    if status == "protocol":
        raise P.ProtocolError(*payload)
    if status == "rig":
        raise RigError(*payload)
    return payload


class RigWorkers:
    """Runs functions of rig work in child processes (module doc): first in `processes` children
    at `SCHED_IDLE`, then, for a call still unanswered after `idle_wait_s`, in as many at the
    background's niceness as well, the first answer winning."""

    def __init__(
        self,
        processes: int = PROCESSES,
        timeout_s: float = TIMEOUT_S,
        idle_wait_s: float = IDLE_WAIT_S,
        answered: Callable[[bool], None] | None = None,
    ):
        self.processes, self.timeout_s, self.idle_wait_s = processes, timeout_s, idle_wait_s
        self.answered = answered  # told, for each call answered, whether an idle child answered it
        self._pools: dict[bool, ProcessPoolExecutor] = {}  # by `idle`
        self.failures = 0  # calls failed by a lost child (died, or killed past the time limit)
        self.promoted = 0  # calls the idle children had not answered within `idle_wait_s`
        self._idle_starved_until = 0.0  # calls skip the idle children until then (`IDLE_BACKOFF_S`)

    def _executor(self, idle: bool) -> ProcessPoolExecutor:
        if (pool := self._pools.get(idle)) is None:
            pool = self._pools[idle] = ProcessPoolExecutor(
                self.processes,
                mp_context=multiprocessing.get_context("forkserver"),
                initializer=_child_start,
                initargs=(background_placement(), os.getpid(), idle),
            )
        return pool

    async def _submit(self, idle: bool, call: tuple) -> tuple[ProcessPoolExecutor, asyncio.Future]:
        pool = self._executor(idle)
        try:
            # submitting may start a child: a fork server round trip, kept off the event loop
            future = await in_background(pool.submit, _call, *call)
        except RuntimeError:  # broken by a child lost since, or shut down by another build
            self._lost(pool)
            pool = self._executor(idle)
            future = await in_background(pool.submit, _call, *call)
        return pool, asyncio.wrap_future(future)

    async def run(self, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        """`fn(*args, **kwargs)` (picklable, as its result) in a child; its `ProtocolError` and
        `RigError` are raised here; a child at normal priority lost meanwhile raises
        `WorkerFailed` (an idle child lost only sends the call on to one)."""
        call = (fn, args, kwargs)
        deadline = time.monotonic() + self.timeout_s
        idle = time.monotonic() >= self._idle_starved_until
        pool, future = await self._submit(idle, call)
        running = {pool: future}  # each pool holding this call, and its future there
        normal_sent = not idle
        try:
            while True:
                wait_s = deadline - time.monotonic()
                if not normal_sent:
                    wait_s = min(wait_s, self.idle_wait_s)
                done, _ = await asyncio.wait(
                    running.values(), timeout=max(wait_s, 0), return_when=asyncio.FIRST_COMPLETED
                )
                for pool, future in list(running.items()):
                    if future in done:
                        del running[pool]
                        if not isinstance(future.exception(), BrokenProcessPool):
                            idle_answered = self._pools.get(True) is pool
                            if idle_answered and time.monotonic() >= self._idle_starved_until:
                                self._retire_normal()
                            if self.answered is not None:
                                self.answered(idle_answered)
                            return _answer(*future.result())
                        self._lost(pool)
                if time.monotonic() >= deadline:
                    for pool in running:
                        self._lost(pool, kill=True)
                    self.failures += 1
                    raise WorkerFailed(f"no answer within {self.timeout_s:g} s")
                if not normal_sent:  # the idle child has not answered in time, or died
                    if running:
                        self.promoted += 1
                        self._idle_starved_until = time.monotonic() + IDLE_BACKOFF_S
                    pool, future = await self._submit(False, call)
                    running[pool], normal_sent = future, True
                elif not running:
                    self.failures += 1
                    raise WorkerFailed("its worker process died")
        finally:
            for future in running.values():  # the slower copy: dropped if it has not started
                future.cancel()

    def _retire_normal(self) -> None:
        """The idle children answer again: the normal ones (120-250 MB each) go once the calls they
        hold are done (`shutdown` without waiting or cancelling), and the next starved call starts
        fresh ones."""
        if (pool := self._pools.pop(False, None)) is not None:
            pool.shutdown(wait=False)

    def _lost(self, pool: ProcessPoolExecutor, kill: bool = False) -> None:
        """Forget a pool that lost a child (the next build starts a fresh one); `kill`: its
        children first (one of them is stuck)."""
        idle = next((key for key, kept in self._pools.items() if kept is pool), None)
        if idle is None:
            return  # another build already replaced it
        del self._pools[idle]
        if kill:
            for pid in list(getattr(pool, "_processes", None) or {}):  # the executor's own children
                with contextlib.suppress(OSError):
                    os.kill(pid, signal.SIGKILL)
        pool.shutdown(wait=False, cancel_futures=True)

    def close(self) -> None:
        for pool in self._pools.values():
            pool.shutdown(wait=False, cancel_futures=True)
        self._pools.clear()


class RigBuilds:
    """Per-caller gates for rig work in child processes (one per runtime, on its loop).
    `runner` runs one unit of that work: `RigWorkers.run` by default."""

    def __init__(
        self, per_caller: int = PER_CALLER, runner: Runner | None = None, answered: Callable[[bool], None] | None = None
    ) -> None:
        self.per_caller = per_caller
        self.workers = RigWorkers(answered=answered)
        self._runner: Runner = runner or self.workers.run
        self._gates: dict[str, asyncio.Semaphore] = {}
        self._users: Counter[str] = Counter()
        self.built = 0  # builds that went to a child (the rest were cached)
        self._refused: OrderedDict[bytes, P.ProtocolError] = OrderedDict()

    async def run(self, caller: str, fn: Callable[..., T], *args, **kwargs) -> T:
        """`fn(*args, **kwargs)` in a child process, within `caller`'s gate."""
        gate = self._gates.get(caller)
        if gate is None:
            gate = self._gates[caller] = asyncio.Semaphore(self.per_caller)
        self._users[caller] += 1
        try:
            async with gate:
                self.built += 1
                return await self._runner(fn, *args, **kwargs)
        finally:
            self._users[caller] -= 1
            if self._users[caller] <= 0:  # the gate goes with its last user: callers come and go
                del self._users[caller]
                del self._gates[caller]

    async def adapter(
        self,
        caller: str,
        skeleton: str | None,
        bvh_header: str | None,
        model_skeleton: Skeleton,
        joints: list[str] | None = None,
        **options,
    ) -> SkeletonAdapter:
        """`skeletons.adapter_for`, in a child unless already cached; raises its typed errors."""
        cached = cached_adapter(skeleton, bvh_header, model_skeleton, joints, **options)
        if cached is not None:
            return cached
        request = json.dumps([skeleton, bvh_header, model_skeleton.names, joints, options], sort_keys=True)
        key = hashlib.blake2b(request.encode(), digest_size=16).digest()
        if (refused := self._refused.get(key)) is not None:
            self._refused.move_to_end(key)
            raise _again(refused)
        try:
            built = await self.run(caller, adapter_for, skeleton, bvh_header, model_skeleton, joints, **options)
        except WorkerFailed:
            raise
        except P.ProtocolError as err:
            self._refused[key] = _again(err)
            while len(self._refused) > REFUSED_KEPT:
                self._refused.popitem(last=False)
            raise
        return adopt(built, skeleton, bvh_header, model_skeleton, joints, **options)

    def close(self) -> None:
        self.workers.close()


def _again(err: P.ProtocolError) -> P.ProtocolError:
    """A copy of its own: a connection marks the error it raises fatal, or names a character."""
    return P.ProtocolError(err.code, err.message, err.seq, err.fatal, err.close_code, err.character)
