"""Open-loop load test: N concurrent sessions, each sending real motion frames on a fixed clock.

Open loop means a session never waits for a reply before sending its next frame, so a slow
server shows up as latency (and drops), not as less load. Sessions are spread over several
client processes so the harness is not the bottleneck; each process reports the CPU it used.
Latency is measured per frame from send to the reply with the same sequence number.

Phases: by default the sessions' clocks are spread evenly over one frame period, as independent
clients' are (a game engine's 60 Hz tick is not synchronised with anyone else's); `--phase
aligned` makes every session send at the same instant, the worst case, where the last frame of
each burst waits for all the others.

    stylestream loadtest --sessions 64 --fps 60 --seconds 10 --model lti
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import multiprocessing as mp
import os
import resource
import struct
import threading
import time
import traceback
import warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from queue import Empty

import numpy as np

PHASES = ("spread", "aligned")
DRAIN_S = 10.0  # after its last frame, how long a session waits for the replies still due


@dataclass
class Result:
    sessions: int
    fps: float
    seconds: float
    sent: int
    received: int
    dropped: int
    late: int  # replies later than one frame period
    lost: int  # sent frames with neither a reply nor a drop count DRAIN_S after the last send
    p50_ms: float
    p95_ms: float
    p99_ms: float
    max_ms: float
    frames_per_s: float
    client_cpu_s: float
    client_processes: int
    server_p50_ms: float = float("nan")  # arrival -> reply sent, from the server's /metrics histogram
    server_p99_ms: float = float("nan")
    server_cpu_s: float = float("nan")
    phase: str = "spread"  # the sessions' clocks: spread over a period, or aligned
    client_behind: int = 0  # frames a client process sent over a period after their slot (harness overloaded)
    characters: int = 1  # per connection: above 1 a crowd (protocol v1.1); counts above are character-frames

    def line(self) -> str:
        crowd = f" x {self.characters} characters" if self.characters > 1 else ""
        return (
            f"sessions {self.sessions:4d}{crowd}  p50 {self.p50_ms:6.2f} ms  p95 {self.p95_ms:6.2f}  p99 {self.p99_ms:6.2f}  "
            f"max {self.max_ms:7.2f}  dropped {self.dropped}  late {self.late}  lost {self.lost}  "
            f"client behind {self.client_behind}  "
            f"{self.frames_per_s:8.0f} frames/s  client cpu {self.client_cpu_s:.1f} s"
        )


def real_frames(n: int = 300, fps: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Hips translation and local rotations of a neutral Bandai Namco walk (validation split), n
    frames; at `fps` (default: the clip's own 30) each frame is the clip's frame at that frame's
    time, held, so the walk plays at its real speed whatever the rate it is sent at. (Sent
    frame by frame at 60 fps, the 30-fps clip walked twice as fast, a 2.1 m/s jog in median.)"""
    from models.data import build_index, load_motion, select

    clip = select(build_index(["bandai-namco-2"]), style="normal", content="walk", split="val")[0]
    m = load_motion(clip)
    step = 1.0 if fps is None else m.fps / fps
    idx = np.floor(np.arange(n) * step + 1e-9).astype(np.int64) % m.num_frames
    return m.translations[idx, 1].astype(np.float32), m.rotations[idx].astype(np.float32)


CAPTURE = ("cmu", "131_02")  # a 120 fps walk (start, walk, stop): real motion at 60 fps and above


def capture_frames(n: int, fps: float) -> tuple[np.ndarray, np.ndarray]:
    """Hips translation and local rotations of a real 120 fps capture (`CAPTURE`) retargeted to
    the model rig, at `fps` (every (120 / fps)-th frame where that is whole, else interpolated),
    n frames, looped. Why not `real_frames` above 30 fps: its 30 fps walk sent at 60 fps repeats
    every other frame, so a 60 fps load carried no 60 fps motion."""
    from models.data import build_index, load_motion, select
    from models.motion.resample import resample
    from models.motion.retarget import retarget

    dataset, name = CAPTURE
    m = load_motion(next(c for c in select(build_index([dataset])) if c.name == name))
    k = m.fps / fps
    m = retarget(m, fps=m.fps)
    if abs(k - round(k)) < 1e-9:
        root, rot = m.translations[:: round(k), 1], m.rotations[:: round(k)]
    else:
        m = resample(m, fps)
        root, rot = m.translations[:, 1], m.rotations
    idx = np.arange(n) % len(rot)
    return root[idx].astype(np.float32), rot[idx].astype(np.float32)


def load_frames(n: int, fps: float) -> tuple[np.ndarray, np.ndarray]:
    """What a load test sends at `fps`: the Bandai Namco walk at 30 fps and below, a real
    capture at its rate above (`capture_frames`)."""
    return real_frames(n, fps) if fps <= 30.0 else capture_frames(n, fps)


async def _session(
    url: str,
    start: dict | None,
    frames: np.ndarray,
    fps: float,
    seconds: float,
    stats: dict,
    offset: float = 0.0,
    clock: asyncio.Future | None = None,
    connected: Callable[[], None] = lambda: None,
    characters: int = 1,
) -> None:
    """One session: connect and start, report `connected()`, wait for the common `clock` (or start
    at once without one), then send frame i at `clock + offset + i / fps` whatever the replies do.
    With `characters` > 1 the session is a crowd: each tick carries that many characters' frames
    (each character its own phase of the walk); a tick's latency is each of its characters'."""
    import websockets

    period = 1.0 / fps
    n = int(seconds * fps)
    sent_at = np.full(n, np.nan)
    got_at = np.full(n, np.nan)
    dropped = behind = 0
    accounted = 0  # ticks answered or reported dropped
    all_accounted = asyncio.Event()
    async with websockets.connect(url, max_size=2**22) as ws:
        if start is not None:
            await ws.send(json.dumps(start))
            reply = json.loads(await ws.recv())
            if reply.get("type") not in ("started", "crowd_started") or reply.get("errors"):
                raise RuntimeError(f"session refused: {reply}")
        crowd = characters > 1
        ids = np.arange(characters, dtype="<u4")
        phases = (ids.astype(np.int64) * 13) % len(frames)  # characters at different points of the walk

        async def receiver() -> None:
            nonlocal dropped, accounted
            while True:
                data = await ws.recv()
                if isinstance(data, str):
                    continue  # control acknowledgements
                if crowd:
                    seq, _, _, d = TICK_HEADER.unpack_from(data)
                else:
                    seq, _, d = struct.unpack_from("<IHH", data)
                accounted += d + bool(np.isnan(got_at[seq]))
                got_at[seq] = time.perf_counter()
                dropped += d * characters  # every character of a dropped tick
                if accounted >= n:
                    all_accounted.set()

        recv_task = asyncio.create_task(receiver())
        connected()
        begin = (time.perf_counter() if clock is None else await clock) + offset
        await asyncio.sleep(max(0.0, begin - time.perf_counter()))
        for i in range(n):
            target = begin + i * period
            delay = target - time.perf_counter()
            if delay > 0:
                await asyncio.sleep(delay)
            elif delay < -period:
                behind += 1  # this process could not keep its own clock: the harness, not the server
            sent_at[i] = time.perf_counter()
            if crowd:
                rows = frames[(phases + i) % len(frames)]
                await ws.send(TICK_HEADER.pack(i, 2, characters, 0) + ids.tobytes() + rows.tobytes())
            else:
                await ws.send(_pack(i, frames[i % len(frames)]))  # the echo server returns it as is
        # the last replies: until every tick is answered or counted dropped (a slow server's
        # replies are late, not lost), at most DRAIN_S
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(all_accounted.wait(), DRAIN_S)
        recv_task.cancel()
    stats["latency"].append(got_at - sent_at)
    stats["dropped"] += dropped
    stats["behind"] += behind


TICK_HEADER = struct.Struct("<IHHI")  # a crowd's tick: seq, kind 2, characters, dropped


def _pack(seq: int, payload: np.ndarray) -> bytes:
    return struct.pack("<IHH", seq, 1, 0) + payload.tobytes()


def _worker(
    url: str,
    start: dict | None,
    offsets: list[float],
    fps: float,
    seconds: float,
    results,
    go,
    frames: tuple[np.ndarray, np.ndarray],
    characters: int = 1,
) -> None:
    """A client process with one session per clock offset in `offsets`, sending `frames` (root,
    rotations). Once all its sessions are connected it puts "ready" on `results` and waits for the
    common clock start on `go`; at the end it puts (latencies, dropped, frames sent behind, CPU s),
    or the traceback if it failed, so the parent never waits on a process that died."""
    try:
        root, rot = frames
        payload = np.concatenate([root, rot.reshape(len(rot), -1)], axis=1).astype("<f4")
        stats = {"latency": [], "dropped": 0, "behind": 0}

        async def main() -> None:
            loop = asyncio.get_running_loop()
            clock = loop.create_future()
            waiting = len(offsets)

            def connected() -> None:
                nonlocal waiting
                waiting -= 1
                if waiting == 0:
                    results.put("ready")
                    # a daemon thread, not the loop's executor: if a session fails, nothing waits for it
                    threading.Thread(
                        target=lambda: loop.call_soon_threadsafe(clock.set_result, go.get()), daemon=True
                    ).start()

            await asyncio.gather(
                *(
                    _session(url, start, payload, fps, seconds, stats, offset, clock, connected, characters)
                    for offset in offsets
                )
            )

        cpu0 = resource.getrusage(resource.RUSAGE_SELF)
        asyncio.run(main())
        cpu1 = resource.getrusage(resource.RUSAGE_SELF)
        lat = np.concatenate(stats["latency"]) if stats["latency"] else np.zeros(0)
        results.put(
            (lat, stats["dropped"], stats["behind"], (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime))
        )
    except BaseException:  # noqa: BLE001 - reported to the parent, which raises it
        results.put(traceback.format_exc())


def clock_offsets(sessions: int, fps: float, phase: str = "spread") -> list[float]:
    """When each session sends its first frame, after the common start: evenly spread over one
    period, or all at once."""
    if phase not in PHASES:
        raise ValueError(f"phase must be one of {PHASES}, got {phase!r}")
    spread = phase == "spread"
    return [k / sessions / fps if spread else 0.0 for k in range(sessions)]


def _next(procs: list, results, deadline: float):
    """The next message from the client processes; raises with a child's traceback if one failed,
    or if one died without a word (killed), or at the deadline."""
    while True:
        try:
            message = results.get(timeout=1.0)
        except Empty:
            if time.monotonic() > deadline or any(p.exitcode not in (None, 0) for p in procs):
                codes = [p.exitcode for p in procs]
                for p in procs:
                    p.kill()
                raise RuntimeError(f"load-test client processes failed or hung (exit codes {codes})") from None
            continue
        if isinstance(message, str) and message != "ready":
            for p in procs:
                p.kill()
            raise RuntimeError(f"a load-test client process failed:\n{message}")
        return message


def run(
    url: str,
    sessions: int,
    fps: float = 60.0,
    seconds: float = 10.0,
    model: str = "lti",
    style: str | None = None,
    processes: int | None = None,
    echo: bool = False,
    phase: str = "spread",
    characters: int = 1,
) -> tuple[Result, np.ndarray]:
    """One open-loop run: `sessions` connections over `processes` client processes (default: one
    per core), all connected before one common clock starts; each a session, or with `characters`
    > 1 a crowd of that many. Returns the summary (counts in character-frames) and every tick's
    round trip in ms (NaN: no reply), session by session in send order."""
    processes = processes or max(1, min(sessions, (os.cpu_count() or 2)))
    start = None if echo else {"type": "start", "model": model, "style": style, "encoding": "binary", "fps": fps}
    if characters > 1 and not echo:
        crowd = [{"id": k, "model": model, "style": style} for k in range(characters)]
        start = {"type": "crowd", "fps": fps, "characters": crowd}
    # read here, once (a machine without the data says so before any client starts); at the send rate
    frames = load_frames(round(300 * fps / 30.0), fps)
    ctx = mp.get_context("spawn")
    results = ctx.Queue()
    offsets = clock_offsets(sessions, fps, phase)
    gos = [ctx.Queue() for _ in range(min(processes, sessions))]  # one clock-start message per process
    # session k goes to process k % processes, so each process has sessions of every phase
    procs = [
        ctx.Process(
            target=_worker, args=(url, start, offsets[i::processes], fps, seconds, results, go, frames, characters)
        )
        for i, go in enumerate(gos)
    ]
    for p in procs:
        p.start()
    deadline = time.monotonic() + 60.0 + 0.05 * sessions
    for _ in procs:  # every session of every process connected and started
        _next(procs, results, deadline)
    t0 = time.perf_counter() + 0.2  # one clock for all (CLOCK_MONOTONIC is shared by processes)
    for go in gos:
        go.put(t0)
    deadline = time.monotonic() + seconds + 60.0
    parts = [_next(procs, results, deadline) for _ in procs]
    for p in procs:
        p.join()
    lat = np.concatenate([p[0] for p in parts]) * 1000.0
    dropped = sum(p[1] for p in parts)
    done = lat[np.isfinite(lat)]
    k = characters  # every count in character-frames: a tick's latency is each of its characters'
    sent = len(lat) * k
    q = np.percentile(done, [50, 95, 99]) if len(done) else [np.nan] * 3
    result = Result(
        sessions=sessions,
        fps=fps,
        seconds=seconds,
        sent=sent,
        received=len(done) * k,
        dropped=dropped,
        late=int((done > 1000.0 / fps).sum()) * k,
        lost=int(sent - len(done) * k - dropped),
        p50_ms=float(q[0]),
        p95_ms=float(q[1]),
        p99_ms=float(q[2]),
        max_ms=float(done.max()) if len(done) else float("nan"),
        frames_per_s=len(done) * k / seconds,
        client_cpu_s=sum(p[3] for p in parts),
        client_processes=len(procs),
        phase=phase,
        client_behind=sum(p[2] for p in parts),
        characters=characters,
    )
    return result, lat


def write_report(results: list[Result], latencies: list[np.ndarray], out: Path) -> None:
    """JSON of every run plus a plot: latency histogram and latency over time of the largest run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps([asdict(r) for r in results], indent=2))
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.5), dpi=90)
    for r, lat in zip(results, latencies):
        finite = lat[np.isfinite(lat)]
        a.hist(finite, bins=np.logspace(-1, 3, 60), histtype="step", label=f"{r.sessions} sessions")
    a.set_xscale("log")
    a.axvline(1000 / results[0].fps, color="k", ls=":", lw=1)
    a.set_xlabel("round trip (ms)")
    a.set_ylabel("frames")
    a.legend(fontsize=7)
    r = results[-1]
    per_session = latencies[-1].reshape(-1, int(r.seconds * r.fps))  # (sessions, frames), send order
    t = np.arange(per_session.shape[1]) / r.fps
    with warnings.catch_warnings():  # frames with no reply in any session are all-NaN columns
        warnings.simplefilter("ignore", RuntimeWarning)
        b.plot(t, np.nanmedian(per_session, axis=0), lw=0.8, label="median over sessions")
        b.plot(t, np.nanmax(per_session, axis=0), lw=0.8, label="max over sessions")
    b.axhline(1000 / r.fps, color="k", ls=":", lw=1)
    b.set_xlabel(f"send time (s), {r.sessions} sessions")
    b.set_ylabel("round trip (ms)")
    b.set_yscale("log")
    b.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out.with_suffix(".png"))
    plt.close(fig)


# --------------------------------------------------------------------------- command line


def free_port() -> int:
    """A free TCP port on loopback."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_ready(base: str, alive, timeout: float = 60.0, require_ok: bool = True) -> None:
    """Poll `base`/readyz until it answers (200, or anything with require_ok=False, for servers
    without that route); fail early if `alive()` turns false."""
    import httpx

    deadline = time.monotonic() + timeout
    while True:
        try:
            if httpx.get(f"{base}/readyz", timeout=1).status_code == 200 or not require_ok:
                return
        except httpx.TransportError:
            pass
        if not alive():
            raise RuntimeError(f"server at {base} exited before it became ready")
        if time.monotonic() > deadline:
            raise RuntimeError(f"server at {base} not ready after {timeout:.0f} s")
        time.sleep(0.05)


def _spawn(module_args: list[str], port: int, env: dict[str, str] | None = None, cwd: Path | None = None):
    import subprocess
    import sys

    proc = subprocess.Popen(
        [sys.executable, "-m", *module_args, "--port", str(port)],
        env={**os.environ, **(env or {})},
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        cwd=cwd,
    )
    try:
        wait_ready(f"http://127.0.0.1:{port}", lambda: proc.poll() is None, require_ok=False)
    except RuntimeError:
        proc.kill()
        raise
    return proc


def server_histogram(base_url: str, model: str) -> dict[float, float]:
    """Cumulative frame-latency bucket counts {upper bound s: count} from the server's /metrics."""
    import httpx

    from .metrics_text import histogram_buckets

    return histogram_buckets(
        httpx.get(f"{base_url}/metrics", timeout=5).text, "stylestream_frame_latency_seconds", model=model
    )


def histogram_quantiles(before: dict[float, float], after: dict[float, float], qs=(0.5, 0.99)) -> list[float]:
    """Quantiles (ms) of the frames served between two scrapes, linear within a bucket."""
    bounds = sorted(after)
    counts = [after[b] - before.get(b, 0.0) for b in bounds]
    total = counts[-1] if counts else 0.0
    out = []
    for q in qs:
        if total <= 0:
            out.append(float("nan"))
            continue
        target, prev_b, prev_c = q * total, 0.0, 0.0
        for b, c in zip(bounds, counts):
            if c >= target:
                hi = b if np.isfinite(b) else prev_b * 2
                out.append(1000 * (prev_b + (hi - prev_b) * (target - prev_c) / max(c - prev_c, 1e-9)))
                break
            prev_b, prev_c = b, c
    return out


def holds(r: Result) -> bool:
    """The capacity criterion: p99 within one frame period, nothing dropped or lost."""
    return r.p99_ms <= 1000.0 / r.fps and r.dropped == 0 and r.lost == 0


def find_max(measure, start: int = 8, limit: int = 4096) -> int:
    """Largest session count n with holds(measure(n)): doubling from `start`, then bisection to
    within ~12%. A count that fails is measured once more before it counts as failed: on a
    shared machine one stall (another process, a page-in) can wreck a single short run, and a
    failure low in the search would otherwise set the capacity for the whole search."""

    def ok(n: int) -> bool:
        return holds(measure(n)) or holds(measure(n))

    best, n, failed = 0, start, None
    while failed is None and n <= limit:
        if ok(n):
            best, n = n, n * 2
        else:
            failed = n
    while failed is not None and failed - best > max(1, best // 8):
        mid = (best + failed) // 2
        if ok(mid):
            best = mid
        else:
            failed = mid
    return best


@contextlib.contextmanager
def spawned_server(batching: bool = True, env: dict[str, str] | None = None, checkout: Path | None = None):
    """`stylestream serve` on a free loopback port (settings as STYLESTREAM_* in `env`; the code
    of another `checkout` of the repository if given); yields (ws url, process)."""
    port = free_port()
    env = {**(env or {}), **({} if batching else {"STYLESTREAM_BATCHING": "false"})}
    if checkout is not None:
        env["PYTHONPATH"] = str(checkout)
    server = _spawn(["clients.cli", "serve", "--log-level", "warning"], port, env, cwd=checkout)
    try:
        yield f"ws://127.0.0.1:{port}/v1/stream", server
    finally:
        server.terminate()
        server.wait(timeout=20)


def process_tree(pid: int) -> list[int]:
    """`pid` and its descendants (a `--workers` supervisor and its workers)."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        with contextlib.suppress(OSError):
            todo += [int(c) for c in Path(f"/proc/{p}/task/{p}/children").read_text().split()]
    return out


def _cpu_seconds(pid: int) -> float:
    """CPU seconds (user + system) of `pid` and its descendants alive now."""
    total = 0.0
    for p in process_tree(pid):
        with contextlib.suppress(OSError):
            fields = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
            total += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return total


def add_loadtest_command(sub) -> None:
    p = sub.add_parser("loadtest", help="open-loop load test: N sessions at a fixed frame rate, latency percentiles")
    p.add_argument("--url", help="ws://host:port/v1/stream of a running server (default: start one here)")
    p.add_argument("--sessions", default="64", help="session count, or a comma list to sweep (e.g. 1,16,64,256)")
    p.add_argument(
        "--characters", type=int, default=1, help="characters per connection (above 1: crowds, protocol v1.1)"
    )
    p.add_argument("--fps", type=float, default=60.0)
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--model", default="lti")
    p.add_argument("--style", help="target style (default: the model's first)")
    p.add_argument("--no-batching", action="store_true", help="started server runs with cross-session batching off")
    p.add_argument("--echo-floor", action="store_true", help="also measure a plain WebSocket echo server (the floor)")
    p.add_argument("--processes", type=int, help="client processes (default: one per core)")
    p.add_argument(
        "--phase",
        choices=PHASES,
        default="spread",
        help="session clocks spread evenly over a frame period (independent clients), or aligned (all "
        "send at once: the worst case)",
    )
    p.add_argument(
        "--find-max",
        action="store_true",
        help="search (doubling, then bisection) for the most sessions that hold p99 <= one frame period with no drops",
    )
    p.add_argument("--out", type=Path, default=Path("out/loadtest"), help="writes OUT.json and OUT.png")
    p.set_defaults(func=_loadtest)


def measure_fn(
    url: str,
    model: str,
    style: str,
    fps: float,
    seconds: float,
    processes: int | None,
    server=None,
    floor: Result | None = None,
    results: list | None = None,
    lats: list | None = None,
    phase: str = "spread",
    characters: int = 1,
):
    """A function n -> Result that runs one open-loop load test against `url` and prints it."""
    base = url.replace("ws", "http", 1).replace("/v1/stream", "")

    def measure(n: int) -> Result:
        cpu0 = _cpu_seconds(server.pid) if server else None
        hist0 = server_histogram(base, model)
        result, lat = run(url, n, fps, seconds, model, style, processes, phase=phase, characters=characters)
        server_cpu = (_cpu_seconds(server.pid) - cpu0) if server else float("nan")
        s50, s99 = histogram_quantiles(hist0, server_histogram(base, model))
        result.server_p50_ms, result.server_p99_ms, result.server_cpu_s = s50, s99, server_cpu
        if results is not None:
            results.append(result)
            lats.append(lat)
        ratio = f"  p99/floor {result.p99_ms / floor.p99_ms:.2f}" if floor else ""
        print(
            f"{model} "
            + result.line()
            + f"  server-side p50 {s50:.2f} p99 {s99:.2f} ms  server cpu {server_cpu:.1f} s"
            + ratio,
            flush=True,
        )
        return result

    return measure


def echo_floor(
    sessions: int, fps: float, seconds: float, processes: int | None = None, phase: str = "spread"
) -> Result:
    port = free_port()
    echo = _spawn(["clients.echo_server"], port)
    try:
        cpu0 = _cpu_seconds(echo.pid)
        floor, _ = run(
            f"ws://127.0.0.1:{port}/v1/stream", sessions, fps, seconds, processes=processes, echo=True, phase=phase
        )
        floor.server_cpu_s = _cpu_seconds(echo.pid) - cpu0
    finally:
        echo.terminate()
    print("echo floor   " + floor.line())
    return floor


def echo_capacity(fps: float, seconds: float, processes: int | None = None) -> tuple[int, list[Result]]:
    """The transport's own ceiling in this harness: the most sessions a plain echo server on the
    same stack holds at `fps` (p99 within a frame period, nothing lost); no model server can
    beat it. Returns it and every run of the search."""
    port = free_port()
    echo = _spawn(["clients.echo_server"], port)
    runs: list[Result] = []

    def measure(n: int) -> Result:
        result, _ = run(f"ws://127.0.0.1:{port}/v1/stream", n, fps, seconds, processes=processes, echo=True)
        print("echo         " + result.line(), flush=True)
        runs.append(result)
        return result

    try:
        return find_max(measure, 8), runs
    finally:
        echo.terminate()


def first_style(url: str, model: str) -> str:
    import httpx

    models = httpx.get(url.replace("ws", "http", 1).replace("/v1/stream", "/v1/models")).json()
    return next(m["styles"][0] for m in models if m["name"] == model)


def _loadtest(args) -> int:
    counts = [int(s) for s in str(args.sessions).split(",")]
    results, lats = [], []
    floor = echo_floor(counts[-1], args.fps, args.seconds, args.processes, args.phase) if args.echo_floor else None
    with contextlib.ExitStack() as stack:
        url, server = (args.url, None) if args.url else stack.enter_context(spawned_server(not args.no_batching))
        measure = measure_fn(
            url,
            args.model,
            args.style or first_style(url, args.model),
            args.fps,
            args.seconds,
            args.processes,
            server,
            floor,
            results,
            lats,
            phase=args.phase,
            characters=args.characters,
        )
        if args.find_max:
            best = find_max(measure, counts[0])
            print(f"largest session count holding p99 <= {1000 / args.fps:.1f} ms with no drops: {best}")
        else:
            for n in counts:
                measure(n)
    write_report(results, lats, args.out)
    print(f"wrote {args.out.with_suffix('.json')} and {args.out.with_suffix('.png')}")
    return 0
