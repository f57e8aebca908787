"""Rigs built off the event loop, a few at a time per caller.

Parsing a client's BVH header and setting up its retargeter took 10 ms for a CMU rig and 170 ms
for a 176 kB one, on the event loop, in a session's `start` or a crowd's `join`: every other
stream waited (45 new rigs per join: the neighbour's p99 x92). Here a rig `adapter_for` has not
seen in that spelling is built on a background thread (`service.background`: lower priority),
and each caller (`Principal.key`) has at most PER_CALLER builds running; its further ones wait
their turn on its own gate, so one tenant's stream of new rigs queues behind itself, not in
front of anyone else's. A rig seen before costs one dict lookup (`skeletons.cached_adapter`), and
so does a rig refused before: its typed error is kept by a digest of the request's text, so a
client sending the same bad rig again and again (hostile_bench's `bad rigs`: each start and join
parsed it anew on a thread) is answered from the dict.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
from collections import Counter, OrderedDict
from collections.abc import Callable
from typing import TypeVar

from models.motion.skeleton import Skeleton

from . import protocol as P
from .background import in_background
from .skeletons import SkeletonAdapter, adapter_for, cached_adapter

PER_CALLER = 1  # one caller's rig builds at once; the background pool has a few threads for all
REFUSED_KEPT = 256  # typed refusals remembered (digests: a 200 kB header costs 16 bytes here)
T = TypeVar("T")


class RigBuilds:
    """Per-caller gates for rig work on background threads (one per runtime, on its loop)."""

    def __init__(self, per_caller: int = PER_CALLER) -> None:
        self.per_caller = per_caller
        self._gates: dict[str, asyncio.Semaphore] = {}
        self._users: Counter[str] = Counter()
        self.built = 0  # builds that went to a thread (the rest were cached)
        self._refused: OrderedDict[bytes, P.ProtocolError] = OrderedDict()

    async def run(self, caller: str, fn: Callable[..., T], *args, **kwargs) -> T:
        """`fn(*args, **kwargs)` on a background thread, within `caller`'s gate."""
        gate = self._gates.get(caller)
        if gate is None:
            gate = self._gates[caller] = asyncio.Semaphore(self.per_caller)
        self._users[caller] += 1
        try:
            async with gate:
                self.built += 1
                return await in_background(fn, *args, **kwargs)
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
        """`skeletons.adapter_for`, off the loop unless already cached; raises its typed errors."""
        cached = cached_adapter(skeleton, bvh_header, model_skeleton, joints, **options)
        if cached is not None:
            return cached
        request = json.dumps([skeleton, bvh_header, model_skeleton.names, joints, options], sort_keys=True)
        key = hashlib.blake2b(request.encode(), digest_size=16).digest()
        if (refused := self._refused.get(key)) is not None:
            self._refused.move_to_end(key)
            raise _again(refused)
        try:
            return await self.run(caller, adapter_for, skeleton, bvh_header, model_skeleton, joints, **options)
        except P.ProtocolError as err:
            self._refused[key] = _again(err)
            while len(self._refused) > REFUSED_KEPT:
                self._refused.popitem(last=False)
            raise


def _again(err: P.ProtocolError) -> P.ProtocolError:
    """A copy of its own: a connection marks the error it raises fatal, or names a character."""
    return P.ProtocolError(err.code, err.message, err.seq, err.fatal, err.close_code, err.character)
