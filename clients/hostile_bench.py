"""What hostile clients cost a healthy one (issue #16): `python -m clients.hostile_bench`.

Starts `stylestream serve` here, streams one healthy LTI session at 60 fps through every phase,
and in each phase runs one attack from other processes: a message flood at full speed, the
worst uploads (absurd frame rates, the largest valid BVH, again and again), a client that floods
resets and never reads, session churn, and 2,000 half-open connections. Each attack comes right
after a quiet period of the same length, and its p99 is put against that period's: over a run of
several minutes the machine's own background load drifts, which a single quiet phase at the start
does not see (`--repeat N` runs every attack N times, each after its own quiet period). Prints, per
attack, the healthy session's round-trip p50/p99, the quiet period's p99 and the ratio, the frames
it got back, the server's resident memory after the quiet period and after the attack, and what
the attacker was answered.

The attackers share this machine's cores with the server, which a remote attacker does not:
`--attacker-nice 19` runs them at the lowest niceness, and `--phases "cpu load"` (not run by default)
runs two busy processes instead of an attack, what CPU load alone costs the healthy session here.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import multiprocessing
import os
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import httpx
import numpy as np
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

from .loadtest import real_frames, spawned_server
from .raw_ws import HandshakeRefused, RawClient, RawSocket

if TYPE_CHECKING:
    from multiprocessing.synchronize import Event

    from models.motion.skeleton import Motion

ENV = {  # short deadlines, so a phase's leftovers are gone before the next one
    "STYLESTREAM_SEND_TIMEOUT_S": "2",
    "STYLESTREAM_HEADER_TIMEOUT_S": "2",
    "STYLESTREAM_IDLE_TIMEOUT_S": "5",
    "STYLESTREAM_FLOOD_COOLDOWN_S": "10",  # the default, said here: the phase after the flood waits it out
}


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


class Healthy(threading.Thread):
    """One session at 60 fps, one frame in flight; keeps each reply's round trip and phase."""

    def __init__(self, url: str, frames: list[str]) -> None:
        super().__init__(daemon=True)
        self.url, self.frames, self.phase = url, frames, "quiet"
        self.rtts: dict[str, list[float]] = {}
        self.stop, self.error = threading.Event(), ""

    def run(self) -> None:
        try:
            with connect(self.url) as ws:
                ws.send(json.dumps({"type": "start", "model": "lti", "style": "elderly"}))
                json.loads(ws.recv(timeout=60))
                seq = 0
                while not self.stop.is_set():
                    t0 = time.perf_counter()
                    ws.send(self.frames[seq % len(self.frames)].replace('"seq": 0', f'"seq": {seq}'))
                    reply = json.loads(ws.recv(timeout=60))
                    assert reply["seq"] == seq, reply
                    self.rtts.setdefault(self.phase, []).append(time.perf_counter() - t0)
                    seq += 1
                    time.sleep(max(0.0, 1 / 60 - (time.perf_counter() - t0)))
        except Exception as exc:  # noqa: BLE001  (reported in the table)
            self.error = f"{type(exc).__name__}: {exc}"


# ---- attacks (each in its own process, `seconds` long; returns what it was answered) -------------


def flood(url: str, frames: list[str], seconds: float) -> Counter:
    seen: Counter = Counter()
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            with connect(url) as ws:
                ws.send(json.dumps({"type": "start", "model": "lti", "style": "elderly"}))
                ws.recv(timeout=30)
                while time.monotonic() < end:
                    for frame in frames:
                        ws.send(frame)
        except ConnectionClosed as exc:
            seen[f"closed {exc.rcvd.code if exc.rcvd else '?'}"] += 1
        except InvalidStatus as exc:  # refused at the handshake: try again at once, as a flood script does
            seen[f"refused {exc.response.status_code}"] += 1
    return seen


def uploads(base: str, bvh_text: str, seconds: float) -> Counter:
    seen: Counter = Counter()
    head, _, rest = bvh_text.partition("Frame Time:")
    slow = head + "Frame Time: 10" + rest[rest.index("\n") :]  # 0.1 fps: 300x its rows at 30 fps
    tiny_fps = {
        "name": "x",
        "model": "lpn",
        "fps": 1e-4,
        "frames": {"root": [[0, 90, 0]] * 60, "rotations": [[[0, 0, 0, 1]] * 22] * 60},
    }
    end, i = time.monotonic() + seconds, 0
    while time.monotonic() < end:
        i += 1
        for r in (
            httpx.post(
                f"{base}/v1/styles", files={"file": ("a.bvh", slow)}, data={"name": f"s{i}", "model": "lpn"}, timeout=60
            ),
            httpx.post(f"{base}/v1/styles", json=tiny_fps, timeout=60),
            httpx.post(
                f"{base}/v1/styles",
                files={"file": ("b.bvh", bvh_text)},
                data={"name": f"big{i}", "model": "lpn"},
                timeout=120,
            ),
        ):
            seen[f"{r.status_code} {r.json().get('code', 'created')}"] += 1
            if r.status_code == 201:
                gone = httpx.delete(f"{base}/v1/styles/lpn.big{i}", timeout=30)
                if gone.status_code != 204:
                    seen[f"delete {gone.status_code}"] += 1
    return seen


def reset_flood_no_read(base: str, seconds: float) -> Counter:
    seen: Counter = Counter()
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            client = RawClient(base)
        except HandshakeRefused as refused:  # closed for flooding a moment ago: cooling down
            seen[f"refused {refused.status}"] += 1
            continue
        client.send_text(json.dumps({"type": "start", "model": "lti", "style": "elderly"}))
        client.sock.settimeout(1.0)
        try:
            while time.monotonic() < end:
                client.send_text('{"type": "reset"}')
            seen["still open at the end"] += 1
        except OSError as exc:
            seen[f"send stopped ({type(exc).__name__})"] += 1
        client.close()
    return seen


def churn(url: str, seconds: float) -> Counter:
    seen: Counter = Counter()
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        with connect(url) as ws:
            ws.send(json.dumps({"type": "start", "model": "lti", "style": "elderly"}))
            reply = json.loads(ws.recv(timeout=30))
            seen[reply["type"] if reply["type"] == "started" else reply["code"]] += 1
    return seen


def half_open(base: str, seconds: float, count: int = 2000) -> Counter:
    sockets = [RawSocket(base) for _ in range(count)]
    time.sleep(seconds)
    closed = sum(s.closed_by_server(timeout=0.01) for s in sockets)
    for s in sockets:
        s.close()
    return Counter({f"{closed}/{count} dropped by the server": 1})


def _spin(stop: Event) -> None:
    while not stop.is_set():
        for _ in range(100_000):
            pass


@contextlib.contextmanager
def busy_processes(count: int) -> Iterator[None]:
    """`count` processes spinning at this process's niceness for as long as the block runs: CPU
    load from beside the server (here, the "cpu load" phase; `tests/busy.py`, the loaded test suite)."""
    ctx = multiprocessing.get_context("spawn")
    stop = ctx.Event()
    procs = [ctx.Process(target=_spin, args=(stop,), daemon=True) for _ in range(count)]
    for p in procs:
        p.start()
    try:
        yield
    finally:
        stop.set()
        for p in procs:
            p.join()


def cpu_load(seconds: float) -> Counter:
    """Not an attack, a reference: two busy processes (at the attacker's niceness), what CPU load
    alone costs the healthy session on this machine."""
    with busy_processes(2):
        time.sleep(seconds)
    return Counter({f"2 busy processes at nice {os.nice(0)}": 1})


def _attack(name: str, args: tuple, out, go, nice: int) -> None:
    os.nice(nice)  # --attacker-nice: the attacker's own CPU is, on a deployment, another machine's
    out.put("ready")  # imports done: they must not count against the phase
    go.wait()
    out.put(dict(ATTACKS[name](*args)))


ATTACKS = {
    "flood": flood,
    "uploads": uploads,
    "no-read resets": reset_flood_no_read,
    "churn": churn,
    "half-open": half_open,
    "cpu load": cpu_load,
}


def largest_bvh() -> str:
    """A valid BVH near the 16 MiB upload limit: a real walk looped to 27,000 rows at 120 fps."""
    from models.data import build_index, load_motion, select

    walk = load_motion(select(build_index(), dataset="bandai-namco-2", style="normal", content="walk", split="val")[0])
    return looped_bvh(walk, 27_000, frame_time="0.00833333")


def looped_bvh(walk: Motion, rows: int, frame_time: str | None = None) -> str:
    """`walk` as a BVH of `rows` motion rows, its own rows over and over (at `frame_time` seconds
    per row if given, else at its own rate): a long, valid upload from a short real clip."""
    from models.motion import bvh
    from models.motion.skeleton import to_bvh

    head, _, body = bvh.dumps(to_bvh(walk)).partition("Frame Time:")
    time_line, _, motion = body.partition("\n")
    lines = motion.rstrip("\n").split("\n")
    head = head.replace(f"Frames: {walk.num_frames}", f"Frames: {rows}")
    if frame_time is not None:
        time_line = f" {frame_time}"
    return f"{head}Frame Time:{time_line}\n" + "\n".join(lines[i % len(lines)] for i in range(rows)) + "\n"


PHASES = ("flood", "uploads", "no-read resets", "churn", "half-open")  # the default; "cpu load" on request


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=6.0, help="length of each phase")
    ap.add_argument("--set", nargs="*", default=[], metavar="NAME=VALUE", help="server settings (STYLESTREAM_NAME)")
    ap.add_argument(
        "--phases", nargs="*", default=list(PHASES), choices=list(ATTACKS), help="attacks to run (default: all)"
    )
    ap.add_argument(
        "--attacker-nice",
        type=int,
        default=0,
        help="the attacking processes' niceness (19: their own CPU, another machine's on a deployment, "
        "barely competes with the server here)",
    )
    ap.add_argument(
        "--repeat",
        type=int,
        default=1,
        help="run each attack this many times, each after a quiet period of its own (its p99 / quiet is "
        "against that period: the machine's background load drifts over a run)",
    )
    ap.add_argument("--checkout", type=Path, help="run the server of another checkout of the repository (before/after)")
    args = ap.parse_args()
    root, rot = real_frames(240, 60.0)  # the healthy session sends at 60 fps: the walk at its own speed
    frames = [
        json.dumps({"type": "frame", "seq": 0, "root": r.tolist(), "rotations": q.tolist()}) for r, q in zip(root, rot)
    ]
    big = largest_bvh()
    ctx = multiprocessing.get_context("spawn")
    styles_dir = tempfile.TemporaryDirectory(prefix="hostile-bench-styles-")  # not `make serve`'s own styles
    env = {
        **ENV,
        "STYLESTREAM_STYLES_DIR": styles_dir.name,
        **{f"STYLESTREAM_{k.upper()}": v for k, v in (kv.split("=", 1) for kv in args.set)},
    }
    with styles_dir, spawned_server(env=env, checkout=args.checkout) as (url, server):
        base = url.replace("ws://", "http://").removesuffix("/v1/stream")
        healthy = Healthy(url, frames)
        healthy.start()
        plans = {
            "flood": (url, frames, args.seconds),
            "uploads": (base, big, args.seconds),
            "no-read resets": (base, args.seconds),
            "churn": (url, args.seconds),
            "half-open": (base, args.seconds),
            "cpu load": (args.seconds,),
        }
        runs = []  # (attack, quiet label, attack label, RSS after quiet, RSS after attack, answered)
        for r in range(args.repeat):
            for name in args.phases:
                label = name if args.repeat == 1 else f"{name} #{r + 1}"
                healthy.phase = f"quiet before {label}"
                time.sleep(args.seconds)
                quiet_rss = rss_mb(server.pid)
                out, go = ctx.Queue(), ctx.Event()
                proc = ctx.Process(target=_attack, args=(name, plans[name], out, go, args.attacker_nice))
                proc.start()
                assert out.get(timeout=120) == "ready"
                healthy.phase = label
                go.set()
                answered = out.get(timeout=600)
                proc.join()
                healthy.phase = f"after {label}"
                time.sleep(3)  # deadlines (2 s) pass, memory settles
                if name in ("flood", "no-read resets"):  # closed for flooding (4429), and every attacker comes
                    # from this address: the next one waits out the cool-down
                    time.sleep(float(env["STYLESTREAM_FLOOD_COOLDOWN_S"]))
                runs.append((name, f"quiet before {label}", label, quiet_rss, rss_mb(server.pid), answered))
        healthy.stop.set()
        healthy.join(timeout=60)
    p99 = {k: float(np.percentile(np.array(v) * 1000, 99)) for k, v in healthy.rtts.items()}
    print(f"healthy session errors: {healthy.error or 'none'}; bystander BVH {len(big) / 2**20:.1f} MiB")
    print(
        f"{'phase':20} {'frames':>6} {'p50 ms':>7} {'p99 ms':>7} {'quiet p99':>9} {'p99/quiet':>9} {'RSS MB':>7}"
        "  attacker was answered"
    )
    for _, quiet, label, quiet_rss, rss, answered in runs:
        rtt = np.array(healthy.rtts.get(label, [np.nan])) * 1000
        print(
            f"{label:20} {len(rtt):6d} {np.percentile(rtt, 50):7.2f} {p99.get(label, np.nan):7.2f} "
            f"{p99.get(quiet, np.nan):9.2f} {p99.get(label, np.nan) / p99.get(quiet, np.nan):9.2f} "
            f"{quiet_rss:4.0f}>{rss:<4.0f}  " + ", ".join(f"{k}: {v}" for k, v in answered.items())
        )
    quiet = [p99[q] for _, q, *_ in runs if q in p99] or [np.nan]
    print(
        f"quiet periods' p99: min {min(quiet):.2f}, median {np.median(quiet):.2f}, max {max(quiet):.2f} ms "
        "(how far this machine moves with no attack at all)"
    )
    if args.repeat > 1:
        for name in args.phases:
            ratios = [p99.get(label, np.nan) / p99.get(q, np.nan) for n, q, label, *_ in runs if n == name]
            print(f"{name:20} p99/quiet over {len(ratios)} runs: median {np.median(ratios):.2f}, max {max(ratios):.2f}")
    print(f"cores: {os.cpu_count()}")


if __name__ == "__main__":
    main()
