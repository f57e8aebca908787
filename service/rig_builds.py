"""Rigs built in a child process, a few at a time per caller.

Parsing a client's BVH header and setting up its retargeter takes 10-30 ms for a CMU rig and
~170 ms for a large one, in a session's `start`, a crowd's `join` or a `POST /v1/skeletons`. On
the event loop every other stream waited (45 new rigs per join: the neighbour's p99 x92); on a
background thread it still held the GIL, handing it to the loop only at the switch interval, so
a neighbour's round trip, which needs the GIL several times, took 2-3x its quiet p99 whenever
new rigs were built (hostile_bench `crowd rigs`, `big rigs`). So the build runs in a child
process (`RigWorkers`: forked from the server's fork server, kept for the next build, at the
background's priority and CPUs), and the loop only unpickles the built adapter (~30 kB, ~0.2 ms).

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


def _child_start(where: Placement, server: int | None = None) -> None:
    """A child's start: the background's priority and CPUs (the streams' core stays theirs), and
    a watch on the server (`_exit_with`)."""
    enter_background(where)
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
    """Runs functions of rig work in `processes` child processes (module doc)."""

    def __init__(self, processes: int = PROCESSES, timeout_s: float = TIMEOUT_S) -> None:
        self.processes, self.timeout_s = processes, timeout_s
        self._pool: ProcessPoolExecutor | None = None
        self.failures = 0  # children lost (died or killed past the time limit)

    def _executor(self) -> ProcessPoolExecutor:
        if self._pool is None:
            self._pool = ProcessPoolExecutor(
                self.processes,
                mp_context=multiprocessing.get_context("forkserver"),
                initializer=_child_start,
                initargs=(background_placement(), os.getpid()),
            )
        return self._pool

    async def run(self, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        """`fn(*args, **kwargs)` (picklable, as its result) in a child; its `ProtocolError` and
        `RigError` are raised here; a child lost meanwhile raises `WorkerFailed`."""
        pool = self._executor()
        try:
            # submitting may start a child: a fork server round trip, kept off the event loop
            future = await in_background(pool.submit, _call, fn, args, kwargs)
        except RuntimeError:  # shut down meanwhile by another build that lost its child
            pool = self._executor()
            future = await in_background(pool.submit, _call, fn, args, kwargs)
        try:
            status, payload = await asyncio.wait_for(asyncio.wrap_future(future), self.timeout_s)
        except BrokenProcessPool:
            self._lost(pool)
            raise WorkerFailed("its worker process died") from None
        except TimeoutError:
            self._lost(pool, kill=True)
            raise WorkerFailed(f"no answer within {self.timeout_s:g} s") from None
        return _answer(status, payload)

    def _lost(self, pool: ProcessPoolExecutor, kill: bool = False) -> None:
        """Forget a pool that lost a child (the next build starts a fresh one); `kill`: its
        children first (one of them is stuck)."""
        if self._pool is not pool:
            return  # another build already replaced it
        self._pool = None
        self.failures += 1
        if kill:
            for pid in list(getattr(pool, "_processes", None) or {}):  # the executor's own children
                with contextlib.suppress(OSError):
                    os.kill(pid, signal.SIGKILL)
        pool.shutdown(wait=False, cancel_futures=True)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None


class RigBuilds:
    """Per-caller gates for rig work in child processes (one per runtime, on its loop).
    `runner` runs one unit of that work: `RigWorkers.run` by default."""

    def __init__(self, per_caller: int = PER_CALLER, runner: Runner | None = None) -> None:
        self.per_caller = per_caller
        self.workers = RigWorkers()
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
