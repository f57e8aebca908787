"""`python -m clients.perf_report` (or `make perf`): regenerate docs/performance.md.

For every committed model: the step cost through the streaming interface (batch 1 and 256), the
session capacity at 60 fps (largest count holding p99 <= 16.7 ms with no drops) with and
without cross-session batching, a session sweep, and, in the same run, the echo floor and the
echo server's own capacity (the transport's ceiling), crowd capacity (many characters per
connection, protocol v1.1) with the server's CPU per character-frame, capacity with 1 and 2
worker processes (sharing a throwaway redis-server, as `--workers` requires) and a py-spy
profile of the loaded server. Everything printed is also written, so the document is only ever what this command
measured.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import platform
import shutil
import subprocess
import tempfile
import threading
import time
from datetime import date
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from models.interface import FrameBatch, style_vector
from models.registry import load_models
from models.settings import REPO_ROOT, get_settings
from service.settings import ServiceSettings

from . import server_profile
from .loadtest import Result, echo_capacity, echo_floor, find_max, free_port, measure_fn, real_frames, spawned_server

SWEEP = (1, 16, 64)
CROWD = 100  # characters per connection in the crowd runs (protocol v1.1)
CROWD_TARGETS = {"lti": 2000, "erd": 1000, "lpn": 400}  # characters at 60 fps, issue 17
PROFILE_SESSIONS = 64  # LTI, batching on: the 64-session target


def step_cost(model, batch: int, steps: int) -> tuple[float, float]:
    """(median, p99) seconds of one `step_batch` over `batch` sessions on a real walk."""
    root, rot = real_frames()
    state = model.init_state(batch)
    weights = np.repeat(style_vector(model, {model.styles()[0]: 1.0})[None], batch, axis=0)
    times = []
    for t in range(steps + 10):
        k = t % len(root)
        frames = FrameBatch(
            np.repeat(root[k : k + 1].astype(np.float64), batch, 0),
            np.repeat(rot[k : k + 1].astype(np.float64), batch, 0),
        )
        t0 = time.perf_counter()
        _, state = model.step_batch(state, frames, weights)
        times.append(time.perf_counter() - t0)
    times = np.array(times[10:])
    return float(np.median(times)), float(np.percentile(times, 99))


def _row(r: Result, floor: Result | None = None) -> str:
    ratio = f"{r.p99_ms / floor.p99_ms:.1f}" if floor else "–"
    return (
        f"| {r.sessions} | {r.phase} | {r.p50_ms:.2f} | {r.p99_ms:.2f} | {r.dropped} | {r.late} | "
        f"{r.server_p50_ms:.2f} / {r.server_p99_ms:.2f} | {r.frames_per_s:.0f} | {r.server_cpu_s:.1f} | "
        f"{cpu_per_frame_us(r):.0f} | {ratio} |"
    )


def cpu_per_frame_us(r: Result) -> float:
    """Server CPU per reply, the server's own cost: unlike latency it hardly depends on what else
    the shared machine runs."""
    return 1e6 * r.server_cpu_s / max(r.received, 1)


def profiled(measure, pid: int, sessions: int, seconds: float) -> dict[str, float] | str:
    """Run `measure(sessions)` while py-spy samples the server once the clock has started;
    the profile's shares by part, or why there is none."""
    out: dict[str, dict[str, float] | str] = {}

    def sample() -> None:
        time.sleep(2.5 + 0.02 * sessions)  # the load test connects every session before its clock starts
        try:
            out["shares"] = server_profile.summarise(server_profile.record([pid], seconds - 1))
        except (RuntimeError, OSError, subprocess.SubprocessError) as exc:
            out["shares"] = f"no profile: {exc}"

    thread = threading.Thread(target=sample)
    thread.start()
    measure(sessions)
    thread.join()
    return out["shares"]


def profile_section(shares: dict[str, float] | str) -> list[str]:
    if isinstance(shares, str):
        return [shares]
    lines = [
        f"A py-spy sample of the server at {PROFILE_SESSIONS} LTI sessions (batching on, spread clocks), its "
        "busy time by part (`clients/server_profile.py`: each sample counts for the innermost frame that names a part):",
        "",
        "| part | share |",
        "|---|---|",
    ]
    lines += [f"| {name} | {share:.0%} |" for name, share in shares.items()]
    return lines + [
        "",
        "The server is one Python process per worker: its event loop saturates one core, and the "
        "echo server's capacity above is the ceiling of this stack in this harness. Per frame, the "
        "server pays what the echo server pays (receive, send, event loop) plus its own parts above; "
        "the model step is batched.",
    ]


def workers_section(models: dict, fps: float, seconds: float) -> list[str]:
    """Capacity with 1 and 2 server processes, both on a throwaway Redis session store (which
    `--workers` > 1 requires; the 1-worker run uses it too, so only the worker count differs)."""
    redis = shutil.which("redis-server")
    if redis is None:
        return ["Not measured: redis-server is not installed (`make servers` installs it)."]
    style = models["lti"].styles()[0]
    caps, crowd_caps = {}, {}
    with tempfile.TemporaryDirectory() as tmp, _redis(redis, tmp) as store:
        for workers in (1, 2):
            env = {"STYLESTREAM_WORKERS": str(workers), "STYLESTREAM_SESSION_STORE": store}
            with spawned_server(True, env) as (url, server):
                measure = measure_fn(url, "lti", style, fps, seconds, None, server, None, None, None)
                caps[workers] = find_max(measure, 8)
                crowd = measure_fn(url, "lti", style, fps, seconds, None, server, None, None, None, characters=CROWD)
                crowd_caps[workers] = find_max(crowd, 2) * CROWD
    return [
        "`stylestream serve --workers N`: N processes on one port (SO_REUSEPORT), each with its own batcher; "
        "the kernel spreads connections over them. Both runs use a Redis session store (snapshots every 30 "
        "frames go to it).",
        "",
        f"| workers | sessions at 60 fps | vs 1 worker | characters in crowds of {CROWD} | vs 1 worker |",
        "|---|---|---|---|---|",
        f"| 1 | {caps[1]} | 1.0× | {crowd_caps[1]:,} | 1.0× |",
        f"| 2 | {caps[2]} | {caps[2] / max(caps[1], 1):.1f}× | {crowd_caps[2]:,} | "
        f"{crowd_caps[2] / max(crowd_caps[1], 1):.1f}× |",
        "",
        f"Cores: {os.cpu_count()}, shared by the server processes and the load test's client processes.",
    ]


def crowd_section(models: dict, fps: float, seconds: float) -> tuple[list[str], dict[str, int]]:
    """Crowd capacity per model: connections of `CROWD` characters each (doubling, then bisection
    over the connection count), and one run at the model's target count for its latency and the
    server's CPU per character-frame. Returns the section and the capacities in characters."""
    caps: dict[str, int] = {}
    rows = []
    for name, model in models.items():
        style = model.styles()[0]
        with spawned_server(True) as (url, server):
            measure = measure_fn(url, name, style, fps, seconds, None, server, None, None, None, characters=CROWD)
            caps[name] = find_max(measure, 2) * CROWD
            target = CROWD_TARGETS.get(name, caps[name])
            at = measure(max(1, target // CROWD))
        rows.append(
            f"| {name} | {caps[name]:,} | {at.sessions} × {CROWD} | {at.p50_ms:.2f} / {at.p99_ms:.2f} | "
            f"{at.server_p50_ms:.2f} / {at.server_p99_ms:.2f} | {at.dropped} | {cpu_per_frame_us(at):.1f} |"
        )
    return [
        f"Connections of {CROWD} characters each (`stylestream loadtest --sessions N --characters {CROWD}`): one "
        "binary tick per connection per frame time carrying every character's frame, one reply per tick; each "
        "character a real walk at its own phase, the first style. Capacity = the most characters holding p99 ≤ "
        f"{1000 / fps:.1f} ms with nothing dropped or lost (search over the connection count); the next columns "
        "are one run at the model's target count.",
        "",
        "| model | capacity (characters) | run at target | p50 / p99 ms | server-side p50 / p99 ms | dropped | "
        "server CPU µs / character-frame |",
        "|---|---|---|---|---|---|---|",
        *rows,
    ], caps


def baseline_section(rev: str, models: dict, fps: float, seconds: float, sessions: int = 48) -> list[str]:
    """The same load (`sessions` LTI, batching on) on the server of `rev` and on this tree's,
    alternating twice, so a busy spell of the shared machine hits both alike."""
    style = models["lti"].styles()[0]
    label = subprocess.run(
        ["git", "log", "-1", "--format=%h %s", rev], cwd=REPO_ROOT, capture_output=True, text=True, check=True
    ).stdout.strip()[:90]
    runs: dict[str, list[Result]] = {"before": [], "after": []}
    with tempfile.TemporaryDirectory() as tmp:
        tree = Path(tmp) / "baseline"
        subprocess.run(
            ["git", "worktree", "add", "--detach", str(tree), rev], cwd=REPO_ROOT, check=True, capture_output=True
        )
        try:
            for _ in range(2):
                for which, checkout in (("before", tree), ("after", None)):
                    with spawned_server(True, checkout=checkout) as (url, server):
                        measure = measure_fn(url, "lti", style, fps, seconds, None, server, None, runs[which], [])
                        measure(sessions)
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(tree)], cwd=REPO_ROOT, capture_output=True)
    cpu = {k: float(np.mean([cpu_per_frame_us(r) for r in v])) for k, v in runs.items()}
    p50 = {k: float(np.mean([r.p50_ms for r in v])) for k, v in runs.items()}
    p99 = {k: float(np.mean([r.p99_ms for r in v])) for k, v in runs.items()}
    return [
        f"{sessions} LTI sessions at {fps:g} fps, batching on, two runs each, alternating; before = `{label}`.",
        "",
        "| server | CPU µs / frame | p50 ms | p99 ms |",
        "|---|---|---|---|",
        f"| before | {cpu['before']:.0f} | {p50['before']:.2f} | {p99['before']:.2f} |",
        f"| after | {cpu['after']:.0f} | {p50['after']:.2f} | {p99['after']:.2f} |",
        f"| after / before | {cpu['after'] / cpu['before']:.2f} | {p50['after'] / p50['before']:.2f} | "
        f"{p99['after'] / p99['before']:.2f} |",
    ]


@contextlib.contextmanager
def _redis(binary: str, folder: str):
    port = free_port()
    proc = subprocess.Popen(
        [binary, "--port", str(port), "--bind", "127.0.0.1", "--dir", folder, "--save", "", "--appendonly", "no"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        time.sleep(0.5)
        yield f"redis://127.0.0.1:{port}/0"
    finally:
        proc.terminate()
        proc.wait(timeout=10)


KEPT = "<!-- The sections below are kept by make perf: each was measured by the command it names. -->"


def _kept_sections(out: Path) -> str:
    """What follows the `KEPT` marker in the current document (hand-run measurements of other
    tools), carried over so a new run does not lose them."""
    old = out.read_text() if out.exists() else ""
    return "\n" + old[old.index(KEPT) :] if KEPT in old else ""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m clients.perf_report", description=__doc__)
    parser.add_argument("--seconds", type=float, default=4.0, help="length of each load run")
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "docs" / "performance.md")
    parser.add_argument(
        "--baseline",
        metavar="REV",
        help="also measure the server of this git revision (a temporary "
        "worktree) against this one, alternating, at the same load: before/after server CPU per frame",
    )
    args = parser.parse_args(argv)
    fps = 60.0
    t_start = time.perf_counter()
    # every committed model: LPN-FiLM, a character controller, also takes frames (it reads its
    # control off the input motion), which is how the load test drives it
    models = load_models(get_settings().weights_dir)
    floor = echo_floor(SWEEP[-1], fps, args.seconds)
    aligned_floor = echo_floor(SWEEP[-1], fps, args.seconds, phase="aligned")
    lines = [
        "# Performance",
        "",
        f"Regenerated by `make perf` (`python -m clients.perf_report`) on {date.today()}, {platform.machine()}, "
        "2 cores, no GPU. Load: open loop, every session sends a frame of real motion at the send rate "
        "(binary; `loadtest.load_frames`: above 30 fps a 120 fps CMU walk retargeted to the model rig and "
        f"decimated to the send rate) on a fixed {fps:g} Hz clock from 2 client processes and never waits for "
        "replies. The sessions' clocks are "
        "spread evenly over one frame period, as independent clients' are; one row per model repeats 64 sessions "
        "with aligned clocks (every session sends at the same instant: the worst case, where each burst's last "
        "frame waits for all the others). Round trip = send to reply; "
        "server-side = frame arrival to reply sent (the server's `/metrics` histogram); capacity = the most "
        f"sessions holding p99 ≤ {1000 / fps:.1f} ms with no drops (doubling, then bisection; a count that fails is run once more before it counts as failed). The echo floor is a "
        "plain WebSocket echo server on the same stack (uvicorn + Starlette, same route), measured in the same run, "
        "as is its capacity (below). "
        f"Sessions announce {fps:g} fps; models run at their own 30 fps, every reply interpolated from their "
        "outputs (docs/protocol.md, Frame rates).",
        "",
        "Echo floor, "
        + ", ".join(
            f"{f.sessions} sessions {f.phase}: p50 {f.p50_ms:.2f} ms, p99 {f.p99_ms:.2f} ms, {f.late} late, client "
            f"CPU {f.client_cpu_s:.1f} s, echo server CPU {cpu_per_frame_us(f):.0f} µs per frame"
            for f in (floor, aligned_floor)
        )
        + ".",
        "",
        "## Model step cost (through the streaming interface, first style)",
        "",
        "| model | batch 1 median / p99 (ms) | batch 256 per frame (µs) | batched frames/s |",
        "|---|---|---|---|",
    ]
    for name, model in models.items():
        # with the server's BLAS thread limit: threads of their own made ERD's batch of 256 ~10x slower
        # on the loaded 2-core machine
        with threadpool_limits(ServiceSettings().blas_threads, user_api="blas"):
            m1, p1 = step_cost(model, 1, 300)
            m256, _ = step_cost(model, 256, 40)
        lines.append(f"| {name} | {m1 * 1e3:.2f} / {p1 * 1e3:.2f} | {m256 / 256 * 1e6:.1f} | {256 / m256:,.0f} |")
        print(f"{name} step: batch 1 {m1 * 1e3:.2f} ms, batch 256 {m256 / 256 * 1e6:.1f} us/frame", flush=True)
    capacity: dict[str, dict[bool, int]] = {}
    at_64: dict[str, Result] = {}
    shares: dict[str, float] | str = "not measured"
    for name in models:
        capacity[name] = {}
        for batching in (True, False):
            with spawned_server(batching) as (url, server):
                style = models[name].styles()[0]
                sweep: list[Result] = []
                measure = measure_fn(url, name, style, fps, args.seconds, None, server, floor, sweep, [])
                capacity[name][batching] = find_max(measure, 8)
                if batching:
                    sweep.clear()
                    for n in SWEEP:
                        measure(n)
                    measure_fn(
                        url, name, style, fps, args.seconds, None, server, aligned_floor, sweep, [], phase="aligned"
                    )(SWEEP[-1])
                    lines += [
                        "",
                        f"## {name}: session sweep, batching on",
                        "",
                        "| sessions | clocks | p50 ms | p99 ms | dropped | late | server-side p50 / p99 ms | "
                        "frames/s | server CPU s | server CPU µs / frame | p99 / echo floor |",
                        "|---|---|---|---|---|---|---|---|---|---|---|",
                    ]
                    lines += [_row(r, floor if r.phase == "spread" else aligned_floor) for r in sweep]
                    at_64[name] = [r for r in sweep if r.sessions == SWEEP[-1]]
                    if name == "lti":
                        shares = profiled(measure, server.pid, PROFILE_SESSIONS, args.seconds)
    echo_cap, _ = echo_capacity(fps, args.seconds)
    lines += [
        "",
        "## Capacity at 60 fps (p99 ≤ 16.7 ms, no drops)",
        "",
        f"The echo server (same stack, no model, no validation) holds **{echo_cap}** sessions in this harness: "
        "the transport's ceiling here, which no model server on this stack can pass.",
        "",
        "| model | batching on | batching off | batching gain | batching on / echo capacity |",
        "|---|---|---|---|---|",
    ]
    for name, cap in capacity.items():
        gain = f"{cap[True] / cap[False]:.1f}×" if cap[False] else "∞"
        lines.append(f"| {name} | {cap[True]} | {cap[False]} | {gain} | {cap[True] / max(echo_cap, 1):.2f} |")
    lines += ["", "## Targets (issue 7)", "", "| target | measured | met |", "|---|---|---|"]
    for name, runs in at_64.items():
        for r in runs:
            ratio = r.p99_ms / (floor if r.phase == "spread" else aligned_floor).p99_ms
            lines.append(
                f"| {name}: 64 sessions at p99 ≤ 2× the echo floor ({r.phase} clocks) | p99 {r.p99_ms:.1f} ms "
                f"= {ratio:.1f}× | {'yes' if ratio <= 2 and r.dropped == 0 else 'no'} |"
            )
    for name, need in (("erd", 256), ("lti", 512)):
        if name in capacity:
            lines.append(
                f"| {name}: ≥ {need} sessions | {capacity[name][True]} | "
                f"{'yes' if capacity[name][True] >= need else 'no'} |"
            )
    for name, cap in capacity.items():
        gain = cap[True] / cap[False] if cap[False] else float("inf")
        lines.append(f"| {name}: batching ≥ 3× unbatched | {gain:.1f}× | {'yes' if gain >= 3 else 'no'} |")
    lines += [
        "",
        f"For scale: the echo server alone holds {echo_cap} sessions in this harness (its client processes "
        "share the same cores), so a session target above that is out of reach for any server on this stack "
        "here, whatever the model costs.",
    ]
    crowd_lines, crowd_caps = crowd_section(models, fps, args.seconds)
    lines += ["", "## Crowds: many characters per connection", "", *crowd_lines]
    lines += ["", "## Targets (issue 17)", "", "| target | measured | met |", "|---|---|---|"]
    for name, need in CROWD_TARGETS.items():
        if name in crowd_caps:
            got = crowd_caps[name]
            lines.append(f"| {name}: ≥ {need:,} characters in crowds | {got:,} | {'yes' if got >= need else 'no'} |")
    for name, cap in capacity.items():
        share = cap[True] / max(echo_cap, 1)
        lines.append(
            f"| {name}: single-character capacity ≥ 0.8× the echo server's ({echo_cap}) | {cap[True]} = "
            f"{share:.2f}× | {'yes' if share >= 0.8 else 'no'} |"
        )
    for name, runs in at_64.items():
        spread = [r for r in runs if r.phase == "spread"]
        if spread:
            ratio = cpu_per_frame_us(spread[0]) / max(cpu_per_frame_us(floor), 1e-9)
            lines.append(
                f"| {name}: server CPU per frame ≤ 1.3× the echo server's, {SWEEP[-1]} single-character sessions | "
                f"{cpu_per_frame_us(spread[0]):.0f} µs vs {cpu_per_frame_us(floor):.0f} µs = {ratio:.2f}× | "
                f"{'yes' if ratio <= 1.3 else 'no'} |"
            )
    lines += ["", "## Worker processes (lti, batching on)", ""] + workers_section(models, fps, args.seconds)
    if args.baseline:
        lines += ["", f"## Before / after: this tree against `{args.baseline}`", ""] + baseline_section(
            args.baseline, models, fps, args.seconds
        )
    lti_64 = at_64.get("lti", [])
    per_frame = (
        f"At 64 LTI sessions (spread clocks) the server spends {cpu_per_frame_us(lti_64[0]):.0f} µs of CPU per "
        f"frame; the echo server spends {cpu_per_frame_us(floor):.0f} µs on the same load."
        if lti_64
        else ""
    )
    lines += (
        ["", "## Where the time goes", "", per_frame]
        + profile_section(shares)
        + [
            "",
            f"Run time of this report: {time.perf_counter() - t_start:.0f} s; load average at the end "
            f"{', '.join(f'{x:.1f}' for x in os.getloadavg())} (the machine is shared).",
        ]
    )
    args.out.write_text("\n".join(lines) + "\n" + _kept_sections(args.out))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
