"""Waiting on a condition instead of sleeping a guessed time: a loaded 2-core machine makes any
fixed delay a race (an event the test just caused may land a little later)."""

from __future__ import annotations

import time
from collections.abc import Callable


def wait_until(check: Callable[[], object], what: str, timeout: float = 10.0, interval: float = 0.02) -> None:
    """Return as soon as `check()` is true; fail, naming `what`, after `timeout` seconds."""
    deadline = time.monotonic() + timeout
    while not check():
        assert time.monotonic() < deadline, f"timed out after {timeout:g} s waiting for {what}"
        time.sleep(interval)
