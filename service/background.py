"""Work the streams must not wait for, on threads (and processes) at a lower CPU priority.

Building a style from an uploaded clip (the FiLM generator over it), writing and reading style
files, fine-tuning, handing a large request's memory back, and the decoding child that turns an
uploaded clip into a motion are CPU work that no frame waits for. On a machine with few cores
the streams' frames wait for whatever else is runnable: on the 2-core test machine two busy
processes cost a healthy session 3.5-4.5x its quiet round-trip p99 at nice 0, up to 2.1x at
nice 10 and nothing measurable at nice 19 (`python -m clients.hostile_bench --phases "cpu load"
--attacker-nice N`, docs/deploy.md).

That work runs at `background_nice` (default 10), not 19, and on all CPUs but one
(`background_cpus`, `placement`). Nice also weighs it against every other
busy process on the machine, and at 19 (1.5 % of a nice-0 process's weight) an upload beside a
few busy processes barely ran: beside four spinning processes the longest clip's upload took 87 s
at 19 and 11 s at 10. What the streams felt of the hostile bench's upload phase did not clearly
differ (p99 / quiet, three alternating pairs, 19 / 10: 1.43 / 1.78, 2.74 / 3.06, 2.13 / 2.04).

Linux gives each thread its own niceness and CPU set (`setpriority`, `sched_setaffinity` on a
thread id); elsewhere the calls are refused and the work simply runs at normal priority anywhere.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import os
import threading
import zipfile
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import ParamSpec, TypeVar

import numpy as np

BACKGROUND_NICE = 10  # `ServiceSettings.background_nice`'s default, and this process's until set
BACKGROUND_CPUS = 0  # `ServiceSettings.background_cpus`'s: all CPUs but one
WORKERS = 4  # two decoding children waited on, a style built and a file written at once

P = ParamSpec("P")
R = TypeVar("R")


@dataclass(frozen=True)
class Placement:
    """Where background work runs: its niceness, and the CPUs it may use (None: any)."""

    niceness: int
    cpus: frozenset[int] | None


def placement(niceness: int = BACKGROUND_NICE, cpus: int = BACKGROUND_CPUS) -> Placement:
    """Background work at `niceness` on the last `cpus` of the CPUs this process may use (0: all
    but one; a process with one CPU, or asked for all, is not confined). Keeping one CPU free of
    it leaves the event loop and the model thread a core no upload competes for, whatever its
    niceness: hostile_bench upload phase (`--seconds 15 --phases uploads --attacker-nice 19`),
    three alternating pairs, healthy p99 3.65 / 2.42, 2.95 / 2.27, 3.10 / 2.45 ms (any CPU /
    confined to one of two), the same twelve 15 MB uploads made each time."""
    if not hasattr(os, "sched_getaffinity"):  # not Linux: no per-thread CPU sets
        return Placement(niceness, None)
    allowed = sorted(os.sched_getaffinity(0))
    count = cpus or len(allowed) - 1
    return Placement(niceness, frozenset(allowed[-count:]) if 0 < count < len(allowed) else None)


_placement = placement()  # this process's, until `set_background` (a serving process: its settings)


def set_background(where: Placement) -> None:
    """Where this process's background work runs from now on (set before any starts: a thread
    keeps the placement it started with)."""
    global _placement
    _placement = where


def background_placement() -> Placement:
    return _placement


def enter_background(where: Placement | None = None) -> None:
    """Move the calling thread (or a forked child's only thread) to `where` (this process's
    background placement by default). Linux sets both per thread; elsewhere, or where refused,
    the thread stays as it is."""
    where = where or _placement
    tid = threading.get_native_id()
    with contextlib.suppress(OSError, AttributeError):  # not Linux, or not allowed
        os.setpriority(os.PRIO_PROCESS, tid, where.niceness)
    if where.cpus is not None:
        with contextlib.suppress(OSError, AttributeError):
            os.sched_setaffinity(tid, where.cpus)


@functools.cache
def _executor() -> ThreadPoolExecutor:
    return ThreadPoolExecutor(WORKERS, thread_name_prefix="background", initializer=enter_background)


async def in_background(fn: Callable[P, R], /, *args: P.args, **kwargs: P.kwargs) -> R:
    """`asyncio.to_thread`, on a background thread (`enter_background`)."""
    return await asyncio.get_running_loop().run_in_executor(_executor(), functools.partial(fn, *args, **kwargs))


# The most a background thread copies in one C call while moving large data (a decoded clip
# from its child, a style file to disk): the event loop waits for the GIL through any one call
PIECE_BYTES = 256 << 10


def pieces(data: memoryview) -> Iterator[memoryview]:
    """`data` (bytes) in views of at most PIECE_BYTES, without copying."""
    for start in range(0, len(data), PIECE_BYTES):
        yield data[start : start + PIECE_BYTES]


def save_npz(path: str | os.PathLike, **arrays: np.ndarray | float) -> None:
    """`np.savez` for a background thread: each array written in pieces, stored uncompressed.
    A thread holds the GIL, and the event loop waits, for the whole of any one C call:
    `np.savez_compressed` copies each array whole (`tobytes`) before compressing, and zlib held it
    in some pieces too. Saving a 9,000-frame clip on a thread made the event loop late by 2.2-5.8
    ms per save that way; stored in pieces, 47 of 48 saves stayed at the loop's idle timer floor
    (~0.9 ms). The clip file is larger for it (~6 MB at most)."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as archive:
        for name, value in arrays.items():
            array = np.asarray(value)
            if not array.flags.c_contiguous:
                array = array.copy(order="C")
            with archive.open(f"{name}.npy", "w", force_zip64=True) as member:
                np.lib.format.write_array_header_2_0(member, np.lib.format.header_data_from_array_1_0(array))
                for piece in pieces(array.data.cast("B")):
                    member.write(piece)
