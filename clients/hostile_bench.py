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

Crowds and custom rigs (issue #48; the server has three tokens, the attackers use one, the
healthy session another): a tenant filling a crowd to its cap and sending 712-character ticks
with a new list each time, then dropping it (`crowd fill`); joins of 45 characters on new CMU
rigs (`crowd rigs`); session starts on 1,800- and 400-joint rigs (`big rigs`); rig previews of a
1,000-deep chain and of new rigs (`rig previews`); a 1e308 OFFSET through POST /v1/skeletons, a
start and a join (`bad rigs`: each a typed error, a hang counted); a session resumed as a crowd
character and dropped before a tick, then resumed again (`crowd resume`: its place kept).
`/healthz` is polled every 100 ms throughout, the half-open phase beyond the server's connection
cap (1,500 here), and every answer other than 200 is counted.

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
import re
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

HEALTHY, ATTACKER = "healthy-token", "attacker-token"  # the server has three tenants (issue #48)
ENV = {  # short deadlines, so a phase's leftovers are gone before the next one
    "STYLESTREAM_API_TOKENS": json.dumps([HEALTHY, ATTACKER, "third-token"]),
    # below the half-open phase's 2,000: /healthz (polled throughout) must answer at the cap
    "STYLESTREAM_MAX_CONNECTIONS": "1500",
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
    http = httpx.Client(headers={"Authorization": f"Bearer {ATTACKER}"})
    while time.monotonic() < end:
        i += 1
        for r in (
            http.post(
                f"{base}/v1/styles", files={"file": ("a.bvh", slow)}, data={"name": f"s{i}", "model": "lpn"}, timeout=60
            ),
            http.post(f"{base}/v1/styles", json=tiny_fps, timeout=60),
            http.post(
                f"{base}/v1/styles",
                files={"file": ("b.bvh", bvh_text)},
                data={"name": f"big{i}", "model": "lpn"},
                timeout=120,
            ),
        ):
            seen[f"{r.status_code} {r.json().get('code', 'created')}"] += 1
            if r.status_code == 201:
                gone = http.delete(f"{base}/v1/styles/lpn.big{i}", timeout=30)
                if gone.status_code != 204:
                    seen[f"delete {gone.status_code}"] += 1
    return seen


def reset_flood_no_read(base: str, seconds: float) -> Counter:
    seen: Counter = Counter()
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            client = RawClient(base, token=ATTACKER)
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


# ---- crowds and custom rigs (issue #48) -----------------------------------------------------------

CROWD_BATCH = 1000  # characters per crowd / join message (well under the 256 KiB message limit)
TICK_CHARACTERS = 712  # characters per tick, a new list each tick


def _rest_floats(joints: int = 22) -> np.ndarray:
    rot = np.tile(np.array([0.0, 0.0, 0.0, 1.0], np.float32), (joints, 1))
    return np.concatenate([np.array([0.0, 92.0, 0.0], np.float32), rot.ravel()])


def _reply(ws, timeout: float = 30) -> dict | bytes:
    """The next reply: a binary tick reply, or a JSON message."""
    raw = ws.recv(timeout=timeout)
    return raw if isinstance(raw, bytes) else json.loads(raw)


def crowd_fill(url: str, seconds: float) -> Counter:
    """One tenant takes every character it may (joins of 1,000 until refused), sends ticks of 712
    characters with a new list each time, then drops the connection (every character stored)."""
    from service import protocol as P

    seen: Counter = Counter()
    end = time.monotonic() + seconds
    spec = lambda i: {"id": i, "model": "lti", "style": "elderly"}  # noqa: E731
    with connect(url, max_size=None) as ws:
        ws.send(json.dumps({"type": "crowd", "characters": [spec(i) for i in range(CROWD_BATCH)]}))
        opened = _reply(ws, 120)
        members = [c["id"] for c in opened["characters"]]
        seen.update(e["code"] for e in opened["errors"])
        while time.monotonic() < end:
            first = len(members)
            ws.send(json.dumps({"type": "join", "characters": [spec(first + i) for i in range(CROWD_BATCH)]}))
            joined = _reply(ws, 120)
            members += [c["id"] for c in joined["characters"]]
            seen.update(f"join refused: {e['code']}" for e in joined["errors"][:1])
            if joined["errors"]:
                break
        seen[f"{len(members)} characters held"] += 1
        frame, seq = _rest_floats(), 0
        while time.monotonic() < end:
            at = (seq * 97) % max(1, len(members) - TICK_CHARACTERS)
            ids = np.array(members[at : at + TICK_CHARACTERS], np.uint32)
            ws.send(P.encode_tick(seq, ids, np.tile(frame, len(ids))))
            while not isinstance(reply := _reply(ws), bytes):
                seen[f"error {reply.get('code')}"] += 1
            seq += 1
        seen["ticks answered"] += seq
    time.sleep(1.0)  # the close (every character stored) falls within the phase
    return seen


def _cmu_header() -> str:
    from models.motion.assets import ASSETS

    return (ASSETS / "cmu.bvh").read_text().split("MOTION")[0] + "MOTION\n"


def _with_offset(header: str, nth: int, offset: str) -> str:
    """The rig with its `nth` OFFSET (0: the root's) set to `offset`."""
    parts = re.split(r"(OFFSET[^\n]*)", header)
    parts[2 * nth + 1] = f"OFFSET {offset}"
    return "".join(parts)


def _distinct(header: str, k: int) -> str:
    """The rig with a root offset of its own: a new rig to the server's cache, the same humanoid."""
    return _with_offset(header, 0, f"{k * 1e-3:.3f} 0 0")


def _with_leaves(header: str, count: int) -> str:
    """The rig with `count` extra leaf joints under its root (a large but valid rig)."""
    leaves = "".join(
        f"JOINT extra{i}\n{{\nOFFSET 0 1 0\nCHANNELS 3 Zrotation Xrotation Yrotation\nEnd Site\n{{\nOFFSET 0 1 0\n}}\n}}\n"
        for i in range(count)
    )
    at = header.index("JOINT")
    return header[:at] + leaves + header[at:]


def crowd_rigs(url: str, seconds: float) -> Counter:
    """Joins of 45 characters, each on a CMU rig never seen before."""
    seen: Counter = Counter()
    header, end, k = _cmu_header(), time.monotonic() + seconds, 0
    with connect(url, max_size=None) as ws:
        ws.send(json.dumps({"type": "crowd", "characters": [{"id": 0, "model": "lti", "style": "elderly"}]}))
        _reply(ws, 60)
        while time.monotonic() < end:
            chars = [
                {"id": 1 + k + i, "model": "lti", "style": "elderly", "bvh_header": _distinct(header, k + i)}
                for i in range(45)
            ]
            k += 45
            ws.send(json.dumps({"type": "join", "characters": chars}))
            joined = _reply(ws, 120)
            if not isinstance(joined, dict) or joined.get("type") != "joined":  # a typed error: counted, then over
                seen[f"join answered {joined.get('code') if isinstance(joined, dict) else 'binary'}"] += 1
                break
            seen["joined"] += len(joined["characters"])
            seen.update(e["code"] for e in joined["errors"])
            ws.send(json.dumps({"type": "leave", "characters": [c["id"] for c in chars]}))
            _reply(ws, 60)
    return seen


def big_rigs(url: str, seconds: float) -> Counter:
    """Session starts on rigs of 1,800 joints (refused) and of 400 (built), each new."""
    seen: Counter = Counter()
    header, end, k = _cmu_header(), time.monotonic() + seconds, 0
    huge, large = _with_leaves(header, 1800), _with_leaves(header, 400)
    while time.monotonic() < end:
        for rig in (huge, large):
            k += 1
            try:
                with connect(url, max_size=None) as ws:
                    start = {"type": "start", "model": "lti", "style": "elderly", "bvh_header": _distinct(rig, k)}
                    ws.send(json.dumps(start))
                    reply = _reply(ws, 120)
                    assert isinstance(reply, dict)
                    seen["started" if reply["type"] == "started" else reply["message"].split(":", 1)[0]] += 1
            except ConnectionClosed as exc:
                seen[f"closed {exc.rcvd.code if exc.rcvd else '?'}"] += 1
            except InvalidStatus as exc:
                seen[f"refused {exc.response.status_code}"] += 1
    return seen


def rig_previews(base: str, seconds: float) -> Counter:
    """POST /v1/skeletons?preview=true with a 1,000-deep chain, and with a CMU rig."""
    seen: Counter = Counter()
    deep = "HIERARCHY\nROOT a\n{\nOFFSET 0 0 0\n" + "JOINT a\n{\nOFFSET 0 1 0\n" * 999 + "}\n" * 1000 + "MOTION\n"
    http = httpx.Client(headers={"Authorization": f"Bearer {ATTACKER}"}, timeout=60)
    end, k = time.monotonic() + seconds, 0
    while time.monotonic() < end:
        for rig in (deep, _distinct(_cmu_header(), k)):
            k += 1
            r = http.post(f"{base}/v1/skeletons", params={"preview": "true"}, json={"bvh_header": rig})
            seen[f"{r.status_code} {r.json().get('code') if r.status_code != 200 else 'png'}"] += 1
    return seen


def bad_rigs(url: str, base: str, seconds: float) -> Counter:
    """A rig with an OFFSET of 1e308, in POST /v1/skeletons, a session's start and a crowd's join:
    each must be a typed error (a hang is counted, after 30 s)."""
    seen: Counter = Counter()
    bad = _with_offset(_cmu_header(), 2, "1e308 0 0")
    http = httpx.Client(headers={"Authorization": f"Bearer {ATTACKER}"}, timeout=60)
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        r = http.post(f"{base}/v1/skeletons", json={"bvh_header": bad})
        seen[f"POST {r.status_code} {r.json().get('code')}"] += 1
        try:
            with connect(url, max_size=None) as ws:
                ws.send(json.dumps({"type": "start", "model": "lti", "style": "elderly", "bvh_header": bad}))
                reply = _reply(ws)
                seen[f"start {reply.get('code') if isinstance(reply, dict) else '?'}"] += 1
            with connect(url, max_size=None) as ws:
                ws.send(json.dumps({"type": "crowd", "characters": [{"id": 0, "model": "lti", "style": "elderly"}]}))
                _reply(ws, 60)
                join = {"id": 1, "model": "lti", "style": "elderly", "bvh_header": bad}
                ws.send(json.dumps({"type": "join", "characters": [join]}))
                reply = _reply(ws)
                seen[f"join {reply['errors'][0]['code'] if isinstance(reply, dict) and reply['errors'] else '?'}"] += 1
        except TimeoutError:
            seen["hang"] += 1
        except ConnectionClosed as exc:  # refused for opening too fast (its token's rate): counted
            seen[f"closed {exc.rcvd.code if exc.rcvd else '?'}"] += 1
        except InvalidStatus as exc:
            seen[f"refused {exc.response.status_code}"] += 1
    return seen


def _resumed(url: str, opening: dict, seconds: float = 10) -> dict:
    """The answer to `opening` (a resume), tried again while the old connection is still being
    closed (`session_in_use`); the connection is left at once, without a frame."""
    deadline = time.monotonic() + seconds
    while True:
        with connect(url, max_size=None) as ws:
            ws.send(json.dumps(opening))
            reply = _reply(ws, 60)
        assert isinstance(reply, dict)
        errors = reply.get("errors") or []
        busy = reply.get("code") == "session_in_use" or any(e["code"] == "session_in_use" for e in errors)
        if not busy or time.monotonic() > deadline:
            return reply
        time.sleep(0.05)


def crowd_resume(url: str, seconds: float) -> Counter:
    """A session of five frames, resumed as a crowd character and dropped without a tick, then
    resumed as a session: its `last_seq` must still be 4 (it was stored as null)."""
    seen: Counter = Counter()
    frame = {"type": "frame", "seq": 0, "root": [0.0, 92.0, 0.0], "rotations": [[0.0, 0.0, 0.0, 1.0]] * 22}
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            with connect(url) as ws:
                ws.send(json.dumps({"type": "start", "model": "lti", "style": "elderly"}))
                started = json.loads(ws.recv(timeout=60))
                if started["type"] != "started":  # e.g. too_many_sessions: the token's rate of new sessions
                    seen[started["code"]] += 1
                    continue
                token = started["resume_token"]
                for seq in range(5):
                    ws.send(json.dumps({**frame, "seq": seq}))
                    ws.recv(timeout=60)
            crowd = {"type": "crowd", "characters": [{"id": 1, "model": "lti", "resume_token": token}]}
            opened = _resumed(url, crowd)
            if not opened.get("characters"):
                seen[f"crowd {opened.get('code') or opened['errors'][0]['code']}"] += 1
                continue
            character = opened["characters"][0]
            again = _resumed(url, {"type": "start", "model": "lti", "resume_token": character["resume_token"]})
            if again["type"] != "started":
                seen[f"resume {again['code']}"] += 1
                continue
            seen["kept its place" if (character["last_seq"], again["last_seq"]) == (4, 4) else "lost it"] += 1
        except ConnectionClosed as exc:
            seen[f"closed {exc.rcvd.code if exc.rcvd else '?'}"] += 1
    return seen


class Prober(threading.Thread):
    """`/healthz` every 100 ms for the whole run: any answer but 200 is counted."""

    def __init__(self, base: str) -> None:
        super().__init__(daemon=True)
        self.base, self.stop, self.answers = base, threading.Event(), Counter()

    def run(self) -> None:
        with httpx.Client(timeout=10) as http:
            while not self.stop.wait(0.1):
                try:
                    self.answers[http.get(f"{self.base}/healthz").status_code] += 1
                except httpx.HTTPError as exc:
                    self.answers[type(exc).__name__] += 1


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
    try:
        out.put(dict(ATTACKS[name](*args)))
    except Exception as exc:  # noqa: BLE001 - reported in the table, not a run left waiting for it
        out.put({f"attack failed: {type(exc).__name__}: {exc}"[:200]: 1})


ATTACKS = {
    "flood": flood,
    "uploads": uploads,
    "no-read resets": reset_flood_no_read,
    "churn": churn,
    "half-open": half_open,
    "crowd fill": crowd_fill,
    "crowd rigs": crowd_rigs,
    "big rigs": big_rigs,
    "rig previews": rig_previews,
    "bad rigs": bad_rigs,
    "crowd resume": crowd_resume,
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


PHASES = (  # the default; "cpu load" on request
    "flood",
    "uploads",
    "no-read resets",
    "churn",
    "half-open",
    "crowd fill",
    "crowd rigs",
    "big rigs",
    "rig previews",
    "bad rigs",
    "crowd resume",
)


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
    with styles_dir, spawned_server(env=env, checkout=args.checkout) as (bare, server):
        base = bare.replace("ws://", "http://").removesuffix("/v1/stream")
        url = f"{bare}?token={ATTACKER}"  # every attacker is one tenant; the healthy session another
        healthy = Healthy(f"{bare}?token={HEALTHY}", frames)
        healthy.start()
        prober = Prober(base)
        prober.start()
        plans = {
            "flood": (url, frames, args.seconds),
            "uploads": (base, big, args.seconds),
            "no-read resets": (base, args.seconds),
            "churn": (url, args.seconds),
            "half-open": (base, args.seconds),
            "crowd fill": (url, args.seconds),
            "crowd rigs": (url, args.seconds),
            "big rigs": (url, args.seconds),
            "rig previews": (base, args.seconds),
            "bad rigs": (url, base, args.seconds),
            "crowd resume": (url, args.seconds),
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
        prober.stop.set()
        prober.join(timeout=30)
        builds = re.findall(
            r'^stylestream_rig_builds_total\{child="(\w+)"\} ([0-9.e+]+)$', httpx.get(f"{base}/metrics").text, re.M
        )
    p99 = {k: float(np.percentile(np.array(v) * 1000, 99)) for k, v in healthy.rtts.items()}
    print(f"healthy session errors: {healthy.error or 'none'}; bystander BVH {len(big) / 2**20:.1f} MiB")
    print("/healthz every 100 ms throughout: " + ", ".join(f"{k}: {v}" for k, v in prober.answers.items()))
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
    print("rigs built, by the child that answered: " + (", ".join(f"{k} {float(v):.0f}" for k, v in builds) or "none"))
    print(f"cores: {os.cpu_count()}")


if __name__ == "__main__":
    main()
