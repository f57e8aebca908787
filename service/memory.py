"""Giving the memory of a large request back to the operating system.

A 15 MB upload is read, copied and freed within one request. glibc serves allocations that large
with mmap at first, but each such free raises its mmap threshold (up to 32 MB), so the next large
bodies come from the heap instead, and freed heap pages stay with the process: after a burst of
uploads the server's resident memory stayed ~150 MB above where it started (issue #16). Trimming
the heap once a large request is done hands those pages back; it costs a walk over the free lists
(about a millisecond), off the event loop.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

_libc = None
if sys.platform.startswith("linux"):
    try:
        _libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:  # not glibc (musl images): nothing to trim with
        _libc = None

LARGE_REQUEST_BYTES = 1 << 20  # from here a request is worth trimming after


def release_freed_memory() -> bool:
    """`malloc_trim(0)` where the C library has it (glibc); True if it gave memory back. The
    foreign call releases the GIL, so run it in a worker thread (`background.in_background`)."""
    trim = getattr(_libc, "malloc_trim", None)
    return bool(trim(0)) if trim is not None else False
