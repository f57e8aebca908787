"""Where a loaded server's time goes: a py-spy sample of the process, summed into a few parts.

py-spy (PyPI, the sampling profiler for Python) reads the process from outside, so the server
runs unchanged. Each sampled stack counts for the part of its innermost frame that names one
(walking from the leaf up: a reply's socket write counts as the send, not as the stream code that
called it); the rest is the event loop itself (uvloop's socket reads, callbacks) and ASGI
plumbing. Only threads doing work count (worker threads waiting for work are left out), so
the shares are of busy time.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from collections import Counter
from pathlib import Path

# (part, markers: substrings of a frame "function (file:line)")
PARTS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("model step (batched)", ("run_step (service/batcher.py",)),
    ("frame decode + validation", ("decode_binary (service/protocol.py", "frame_arrays (service/protocol.py")),
    ("reply encode", ("encode_binary (service/protocol.py", "frame_message (service/protocol.py")),
    (
        "WebSocket send (uvicorn, socket write)",
        ("send (uvicorn/protocols/websockets", "write_binary (service/transport.py"),  # the latter: direct-path replies
    ),
    (
        "WebSocket receive (uvicorn, Starlette)",
        (
            "receive (uvicorn/protocols/websockets",
            "data_received (uvicorn/protocols/websockets",
            "receive (starlette/websockets.py",
        ),
    ),
    ("metrics", ("prometheus_client/",)),
    ("batcher gather/scatter", ("service/batcher.py",)),
    (
        "session bookkeeping (stream, sessions, skeletons)",
        ("service/stream.py", "service/sessions.py", "service/skeletons.py", "service/runtime.py"),
    ),
)
OTHER = "event loop, asyncio, ASGI/Starlette plumbing"
# leaf frames of worker threads waiting for work (the model-step thread, anyio's pool): py-spy's
# idle detection misses some of these lock waits, and they are not busy time
IDLE_LEAVES = ("Condition.wait (threading.py", "_worker (concurrent/futures/thread.py", "Queue.get (queue.py")


def py_spy() -> str | None:
    """The py-spy executable next to this Python, or on PATH."""
    local = Path(sys.executable).with_name("py-spy")
    return str(local) if local.exists() else shutil.which("py-spy")


def record(pids: list[int], seconds: float, rate: int = 200) -> Counter[str]:
    """Sampled stacks of `pids` for `seconds`, as {"frame;frame;...": count} (py-spy raw format)."""
    exe = py_spy()
    if exe is None:
        raise RuntimeError("py-spy not installed")
    stacks: Counter[str] = Counter()
    with tempfile.TemporaryDirectory() as tmp:
        procs = [
            (
                subprocess.Popen(
                    [
                        exe,
                        "record",
                        "-p",
                        str(pid),
                        "-d",
                        str(max(1, round(seconds))),
                        "-r",
                        str(rate),
                        "-f",
                        "raw",
                        "--nonblocking",
                        "-o",
                        f"{tmp}/{pid}.txt",
                    ],
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.PIPE,
                    text=True,
                ),
                pid,
            )
            for pid in pids
        ]
        for proc, pid in procs:
            _, err = proc.communicate(timeout=seconds + 60)
            out = Path(f"{tmp}/{pid}.txt")
            if proc.returncode != 0 or not out.exists():
                raise RuntimeError(f"py-spy failed on pid {pid}: {err.strip()[-300:]}")
            for line in out.read_text().splitlines():
                stack, _, count = line.rpartition(" ")
                stacks[stack] += int(count)
    return stacks


def summarise(stacks: Counter[str]) -> dict[str, float]:
    """Share of samples per part (PARTS order, then OTHER), summing to 1."""
    parts: Counter[str] = Counter()
    for stack, count in stacks.items():
        frames = stack.split(";")
        if not any(frames[-1].startswith(leaf) for leaf in IDLE_LEAVES):
            parts[_part(frames)] += count
    total = sum(parts.values()) or 1
    return {name: parts[name] / total for name, _ in PARTS + ((OTHER, ()),)}


def _part(frames: list[str]) -> str:
    for frame in reversed(frames):  # leaf first
        for name, markers in PARTS:
            if any(m in frame for m in markers):
                return name
    return OTHER
