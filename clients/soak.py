"""Soak test: N sessions streaming for a long time while the server's memory is sampled.

A leak shows up as memory that keeps rising after warm-up, so the soak reports the RSS slope
(least-squares, MB per hour) over the samples after warm-up, not just start and end. Sessions
are closed and reopened every `--session-seconds` (staggered), so per-session allocations,
resume snapshots and their expiry are exercised as well as the per-frame path.

    stylestream soak --minutes 30 --sessions 16 --fps 30 --model lti

Writes OUT.json (every sample), OUT.png (RSS and Python heap over time) and, with --doc, a
markdown page with the figure and the numbers.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import platform
import time
from dataclasses import asdict, dataclass
from datetime import date
from pathlib import Path

import numpy as np

from .loadtest import _session, first_style, real_frames, spawned_server
from .metrics_text import metric_values

MB = 1024 * 1024


@dataclass
class Sample:
    t_s: float  # since the soak began
    rss_mb: float
    heap_blocks: float  # Python allocator blocks in use (stylestream_python_allocated_blocks)
    gc_objects_collected: float
    sessions: float  # open sessions, all models
    frames: float  # frames stylised since the server started


@dataclass
class Summary:
    minutes: float
    sessions: int
    fps: float
    model: str
    samples: int
    warmup_min: float
    start_rss_mb: float
    end_rss_mb: float
    peak_rss_mb: float
    rss_slope_mb_per_h: float  # after warm-up
    rss_slope_last_third_mb_per_h: float  # has it levelled off?
    heap_slope_blocks_per_h: float  # after warm-up
    frames: int
    client_dropped: int
    client_p50_ms: float
    client_p99_ms: float
    load_average: tuple[float, float]  # the machine's 15-minute load average at start and end (shared machines)


# ---- pure helpers ----------------------------------------------------------------------------


def proc_rss_mb(pid: int) -> float:
    """Resident set size of a local process, from /proc/<pid>/status (VmRSS, in kB)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"no VmRSS for pid {pid}")


def slope_per_hour(t_s: np.ndarray, values: np.ndarray, warmup_s: float) -> float:
    """Least-squares slope of `values` against time after `warmup_s`, per hour (nan if < 3 points)."""
    keep = t_s >= warmup_s
    if keep.sum() < 3:
        return float("nan")
    return float(np.polyfit(t_s[keep] / 3600.0, values[keep], 1)[0])


def summarise(
    samples: list[Sample],
    latencies_ms: np.ndarray,
    dropped: int,
    warmup_s: float,
    *,
    minutes: float,
    sessions: int,
    fps: float,
    model: str,
    load_average: tuple[float, float],
) -> Summary:
    t = np.array([s.t_s for s in samples])
    rss = np.array([s.rss_mb for s in samples])
    heap = np.array([s.heap_blocks for s in samples])
    done = latencies_ms[np.isfinite(latencies_ms)]
    q50, q99 = np.percentile(done, [50, 99]) if len(done) else (float("nan"),) * 2
    return Summary(
        minutes=minutes,
        sessions=sessions,
        fps=fps,
        model=model,
        samples=len(samples),
        warmup_min=warmup_s / 60,
        start_rss_mb=float(rss[0]),
        end_rss_mb=float(rss[-1]),
        peak_rss_mb=float(rss.max()),
        rss_slope_mb_per_h=slope_per_hour(t, rss, warmup_s),
        rss_slope_last_third_mb_per_h=slope_per_hour(t, rss, t[-1] * 2 / 3),
        heap_slope_blocks_per_h=slope_per_hour(t, heap, warmup_s),
        frames=int(samples[-1].frames - samples[0].frames),
        client_dropped=dropped,
        client_p50_ms=float(q50),
        client_p99_ms=float(q99),
        load_average=load_average,
    )


# ---- running -----------------------------------------------------------------------------------


async def _sample(base: str, pid: int | None, t0: float) -> Sample:
    import httpx

    async with httpx.AsyncClient(timeout=10) as client:
        m = metric_values((await client.get(f"{base}/metrics")).text)
    rss = proc_rss_mb(pid) if pid is not None else m["process_resident_memory_bytes"] / MB
    return Sample(
        t_s=time.perf_counter() - t0,
        rss_mb=rss,
        heap_blocks=m.get("stylestream_python_allocated_blocks", np.nan),
        gc_objects_collected=m.get("python_gc_objects_collected_total", np.nan),
        sessions=m.get("stylestream_active_sessions", 0.0),
        frames=m.get("stylestream_frames_total", 0.0),
    )


async def soak(
    url: str,
    pid: int | None,
    minutes: float,
    sessions: int,
    fps: float,
    model: str,
    style: str,
    session_seconds: float,
    interval_s: float,
) -> tuple[list[Sample], np.ndarray, int]:
    """Stream `sessions` open-loop sessions (loadtest's session, reopened every `session_seconds`,
    staggered) for `minutes`, sampling the server every `interval_s`. Returns (samples, client
    round trips in ms, frames the server reported dropped)."""
    root, rot = real_frames(round(300 * fps / 30.0), fps)  # the walk at its own speed at `fps`
    payload = np.concatenate([root, rot.reshape(len(rot), -1)], axis=1).astype("<f4")
    start = {"type": "start", "model": model, "style": style, "encoding": "binary", "fps": fps}
    base = url.replace("ws", "http", 1).replace("/v1/stream", "")
    stats = {"latency": [], "dropped": 0, "behind": 0}
    t0 = time.perf_counter()
    end = t0 + minutes * 60

    async def stream_slot(i: int) -> None:
        length = session_seconds * (i + 1) / sessions  # staggered first session, then full length
        while (left := end - time.perf_counter()) > 1.0:
            await _session(url, start, payload, fps, min(length, left - 0.5), stats)
            length = session_seconds

    samples = [await _sample(base, pid, t0)]
    streams = asyncio.gather(*(stream_slot(i) for i in range(sessions)))
    while not streams.done():
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(asyncio.shield(streams), timeout=interval_s)
        samples.append(await _sample(base, pid, t0))
        s = samples[-1]
        print(
            f"{s.t_s / 60:6.1f} min  rss {s.rss_mb:7.1f} MB  heap {s.heap_blocks:9.0f} blocks  "
            f"sessions {s.sessions:3.0f}  frames {s.frames:9.0f}",
            flush=True,
        )
    await streams  # re-raise a session's failure
    latency = np.concatenate(stats["latency"]) * 1000 if stats["latency"] else np.zeros(0)
    return samples, latency, stats["dropped"]


# ---- report ------------------------------------------------------------------------------------


def _zoom(values: list[float], span: float) -> tuple[float, float]:
    """An axis range `span` wide (wider if the data need it) with the data in its lower part."""
    lo, hi = min(values), max(values)
    return lo - 0.1 * max(span, hi - lo), lo + max(span, 1.2 * (hi - lo))


def write_outputs(samples: list[Sample], summary: Summary, out: Path) -> None:
    """OUT.json (summary and every sample) and OUT.png (RSS, Python heap and sessions over time)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(
        json.dumps({"summary": asdict(summary), "samples": [asdict(s) for s in samples]}, indent=1)
    )
    t = np.array([s.t_s for s in samples]) / 60
    fig, (a, b) = plt.subplots(2, 1, figsize=(8, 5), dpi=90, sharex=True, height_ratios=[3, 1])
    a.plot(t, [s.rss_mb for s in samples], lw=1.2, color="C0", label="server RSS (MB)")
    a.axvline(summary.warmup_min, color="k", ls=":", lw=1)
    a.set_ylabel("RSS (MB)", color="C0")
    a.set_ylim(*_zoom([s.rss_mb for s in samples], span=40.0))  # a fixed 40 MB window: small drifts show
    h = a.twinx()
    h.plot(t, [s.heap_blocks / 1e3 for s in samples], lw=1, color="C1", label="Python heap (k blocks)")
    h.set_ylabel("Python heap (k blocks)", color="C1")
    h.set_ylim(*_zoom([s.heap_blocks / 1e3 for s in samples], span=100.0))
    a.set_title(
        f"{summary.sessions} {summary.model} sessions at {summary.fps:g} fps: RSS slope after warm-up "
        f"{summary.rss_slope_mb_per_h:+.1f} MB/h",
        fontsize=9,
    )
    b.plot(t, [s.sessions for s in samples], lw=1, color="C2")
    b.set_ylabel("open sessions")
    b.set_xlabel("minutes")
    fig.tight_layout()
    fig.savefig(out.with_suffix(".png"))
    plt.close(fig)


def markdown(summary: Summary, figure: str, command: str, session_seconds: float) -> str:
    s = summary
    method = (
        f"Measured {date.today().isoformat()} on {platform.machine()} ({platform.python_implementation()} "
        f"{platform.python_version()}) with `{command}`: {s.sessions} open-loop sessions of `{s.model}` at "
        f"{s.fps:g} fps for {s.minutes:g} minutes, each session closed (without `end`, so its resume snapshot "
        f"is kept) and reopened every {session_seconds:g} s, staggered. The server process's RSS is read from "
        "`/proc/<pid>/status` every sample; the Python heap is `stylestream_python_allocated_blocks` from `/metrics`."
    )
    return "\n".join(
        [
            "# Soak: memory over a long run",
            "",
            method,
            "",
            f"![server RSS and Python heap over the soak]({figure})",
            "",
            "| | |",
            "|---|---|",
            f"| RSS at start / end / peak | {s.start_rss_mb:.1f} / {s.end_rss_mb:.1f} / {s.peak_rss_mb:.1f} MB |",
            f"| RSS slope after {s.warmup_min:.1f} min warm-up (least squares) | {s.rss_slope_mb_per_h:+.2f} MB/h |",
            f"| RSS slope over the last third | {s.rss_slope_last_third_mb_per_h:+.2f} MB/h |",
            f"| Python heap slope after warm-up | {s.heap_slope_blocks_per_h:+.0f} blocks/h |",
            f"| frames stylised | {s.frames} |",
            f"| client round trip p50 / p99 | {s.client_p50_ms:.2f} / {s.client_p99_ms:.2f} ms |",
            f"| frames dropped (backpressure) | {s.client_dropped} |",
            f"| samples | {s.samples} |",
            f"| machine load average (15 min) at start / end, {os.cpu_count()} cores | {s.load_average[0]:.1f} / {s.load_average[1]:.1f} |",
            "",
        ]
    )


def add_soak_command(sub) -> None:
    p = sub.add_parser("soak", help="long run of N streaming sessions, sampling server memory (RSS, Python heap)")
    p.add_argument("--url", help="ws://host:port/v1/stream of a running server (default: start one here)")
    p.add_argument(
        "--pid",
        type=int,
        help="with --url: the server's pid on this machine, for RSS from /proc "
        "(default: process_resident_memory_bytes from /metrics)",
    )
    p.add_argument("--minutes", type=float, default=30.0)
    p.add_argument("--sessions", type=int, default=16)
    p.add_argument("--fps", type=float, default=30.0)
    p.add_argument("--model", default="lti")
    p.add_argument("--style", help="target style (default: the model's first)")
    p.add_argument("--session-seconds", type=float, default=60.0, help="each session is reopened after this long")
    p.add_argument("--interval", type=float, default=10.0, help="seconds between memory samples")
    p.add_argument(
        "--warmup", type=float, help="minutes left out of the slope (default: a sixth of the run, at most 5)"
    )
    p.add_argument("--out", type=Path, default=Path("out/soak"), help="writes OUT.json and OUT.png")
    p.add_argument("--doc", type=Path, help="also write this markdown page (e.g. docs/soak.md) with the figure")
    p.set_defaults(func=_soak)


def _soak(args) -> int:
    import sys

    with contextlib.ExitStack() as stack:
        url, pid = args.url, args.pid
        if url is None:
            url, server = stack.enter_context(spawned_server())
            pid = server.pid
        style = args.style or first_style(url, args.model)
        load_start = os.getloadavg()[2]
        samples, latency, dropped = asyncio.run(
            soak(
                url, pid, args.minutes, args.sessions, args.fps, args.model, style, args.session_seconds, args.interval
            )
        )
    warmup_min = args.warmup if args.warmup is not None else min(5.0, args.minutes / 6)
    summary = summarise(
        samples,
        latency,
        dropped,
        warmup_min * 60,
        minutes=args.minutes,
        sessions=args.sessions,
        fps=args.fps,
        model=args.model,
        load_average=(load_start, os.getloadavg()[2]),
    )
    write_outputs(samples, summary, args.out)
    print(json.dumps(asdict(summary), indent=1))
    print(f"wrote {args.out.with_suffix('.json')} and {args.out.with_suffix('.png')}")
    if args.doc:
        png = args.out.with_suffix(".png")
        figure = (
            Path(*png.resolve().parts[len(args.doc.resolve().parent.parts) :])
            if png.resolve().is_relative_to(args.doc.resolve().parent)
            else png.resolve()
        )
        command = "stylestream " + " ".join(sys.argv[1:])
        args.doc.write_text(markdown(summary, figure.as_posix(), command, args.session_seconds))
        print(f"wrote {args.doc}")
    return 0
