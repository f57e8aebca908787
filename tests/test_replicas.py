"""Two replicas sharing a Redis session store and a styles folder behind nginx: a client keeps
streaming through a SIGKILL of the replica holding its session, with one reconnect and the outputs
of an uninterrupted run, also on a style uploaded through the load balancer. Also the SDK's replay
buffer on its own."""

from __future__ import annotations

import signal
import threading
import time

import httpx
import numpy as np
import pytest

from clients.sdk import Character, Client, ReplayBuffer, ResumeError
from models.data import load_motion, select

from .clips import frames_json
from .cluster import nginx, redis_server, replicas, require
from .waiting import wait_until

FRAMES = 150  # 5 s at 30 fps
KILL_AFTER = 47  # replies received before the kill: snapshots at frames 29 (acknowledged) and 59 (not yet)
STYLE_AT = 35  # a style change after the last snapshot before the kill: the resume must replay it too


def stream(base: str, root, rot, on_reply=None, fps: float = 30.0):
    """Stream a clip through one SDK session at `fps`, changing style on the way; outputs, reply
    times and the reconnects made by each reply."""
    outputs, times, reconnects = [], [], []
    with Client(base).session(model="lti", style="elderly") as session:
        next_at = time.perf_counter()
        for t in range(len(root)):
            if t == STYLE_AT:
                session.set_style("exhausted", transition_frames=20)
            frame = session.stylise(root[t], rot[t])
            times.append(time.perf_counter())
            reconnects.append(session.reconnects)
            outputs.append(np.concatenate([frame.root, frame.rotations.ravel()]))
            if on_reply:
                on_reply(t)
            next_at += 1 / fps
            time.sleep(max(0.0, next_at - time.perf_counter()))
    return np.array(outputs), np.array(times), np.array(reconnects)


@pytest.fixture()
def cluster(tmp_path):
    """A fresh cluster per test: each kills a replica."""
    require("redis-server", "nginx")
    with (
        redis_server(tmp_path) as store,
        replicas(tmp_path, 2, session_store=store, styles_dir=tmp_path / "styles", styles_refresh_s=1) as (a, b),
        nginx(tmp_path, [a.port, b.port]) as lb,
    ):
        yield lb, a, b


class HolderKiller:
    """SIGKILLs the replica holding the (one) session 15 ms after the reply to frame `after - 1`,
    mid-way between two frames, so one may be in flight."""

    def __init__(self, servers, after: int) -> None:
        self.servers, self.after, self.replica, self.at = servers, after, None, None

    def __call__(self, t: int) -> None:
        if t + 1 == self.after:
            self.replica = next(s for s in self.servers if s.metric("stylestream_active_sessions") == 1)
            threading.Timer(0.015, self._kill).start()

    def _kill(self) -> None:
        self.replica.signal(signal.SIGKILL)
        self.at = time.perf_counter()


def test_a_session_survives_a_replica_kill_with_one_reconnect_and_unchanged_output(cluster, bn_walk):
    lb, *servers = cluster
    root, rot = bn_walk.translations[:FRAMES, 1], bn_walk.rotations[:FRAMES]
    want, _, _ = stream(lb, root, rot)
    # the first session's close may still be in flight: the killer finds the holder by its gauge
    wait_until(lambda: all(s.metric("stylestream_active_sessions") == 0 for s in servers), "first session closed", 30)

    killer = HolderKiller(servers, KILL_AFTER)
    got, times, reconnects = stream(lb, root, rot, on_reply=killer)
    killer.replica.proc.wait(timeout=10)
    survivor = next(s for s in servers if s is not killer.replica)
    resumed_after = times[reconnects > 0][0] - killer.at
    print(f"\nresume time (SIGKILL -> first resumed frame): {resumed_after * 1000:.0f} ms")

    assert reconnects[-1] == 1
    assert survivor.metric("stylestream_sessions_resumed_total") == 1
    np.testing.assert_allclose(got, want, atol=1e-4)  # float32 on the wire, same computation
    assert resumed_after < 2.0


def test_a_session_on_an_uploaded_style_survives_a_replica_kill(cluster, index):
    """The style was uploaded through nginx to one replica; the session on it, driven as an LPN-FiLM
    controller, resumes on the other after a SIGKILL and goes on as if nothing happened."""
    lb, *servers = cluster
    m = load_motion(select(index, dataset="bandai-namco-1", style="chimpira", content="walk")[0]).slice(0, 150)
    body = {"name": "street", "model": "lpn", "fps": 30, "frames": frames_json(m)}
    assert httpx.post(f"{lb}/v1/styles", json=body, timeout=60).status_code == 201
    ticks = [((1.3, 0.0), 0.02 * t, "walk") for t in range(90)]

    def drive(on_reply=None):
        outputs, reconnects = [], []
        with Client(lb).session(model="lpn", style="street") as session:
            next_at = time.perf_counter()
            for t, (velocity, facing, gait) in enumerate(ticks):
                frame = session.control(velocity, facing, gait)
                outputs.append(np.concatenate([frame.root, frame.rotations.ravel()]))
                reconnects.append(session.reconnects)
                if on_reply:
                    on_reply(t)
                next_at += 1 / 30
                time.sleep(max(0.0, next_at - time.perf_counter()))
        return np.array(outputs), reconnects

    want, _ = drive()
    killer = HolderKiller(servers, KILL_AFTER)
    got, reconnects = drive(on_reply=killer)
    assert killer.replica is not None and reconnects[-1] == 1
    np.testing.assert_allclose(got, want, atol=1e-4)


# ---- the SDK's replay buffer --------------------------------------------------------------
def test_replay_sends_what_follows_the_snapshot_frame_including_style_changes():
    buf = ReplayBuffer()
    for seq in range(5):
        buf.add(seq, f"frame{seq}".encode())
    buf.add(None, "style")
    buf.add(5, b"frame5")
    assert [m for _, m in buf.after(3)] == [b"frame4", "style", b"frame5"]
    assert buf.after(None)[0][1] == b"frame0"  # no frame saved yet: everything


def test_acknowledged_frames_are_forgotten_and_a_snapshot_at_them_still_resumes():
    buf = ReplayBuffer()
    for seq in range(6):
        buf.add(seq, seq)
    buf.acknowledged(3)
    assert [s for s, _ in buf.entries] == [4, 5]
    assert [s for s, _ in buf.after(3)] == [4, 5]
    with pytest.raises(ResumeError):
        buf.after(2)  # older than what the server acknowledged: cannot happen unless the store lost it


def test_an_overflowing_buffer_says_it_cannot_resume_exactly():
    buf = ReplayBuffer(limit=4)
    for seq in range(10):
        buf.add(seq, seq)
    assert len(buf.entries) == 4 and buf.base == 5
    assert [s for s, _ in buf.after(7)] == [8, 9]
    with pytest.raises(ResumeError, match="unacknowledged"):
        buf.after(1)


def test_a_crowd_survives_a_replica_kill_with_one_reconnect_and_unchanged_output(cluster, bn_walk):
    """SIGKILL of the replica holding a crowd: its characters were last stored up to 30 ticks
    before (each crowd stores at a phase of its own), a style change came at 35; the SDK comes
    back through nginx on the other replica, resumes every character and sends again the ticks
    after the store (and the style change if it came later), so the replies equal an
    uninterrupted crowd's exactly."""
    lb, *servers = cluster
    chars = [Character(0, "lti", "elderly"), Character(1, "erd", "exhausted"), Character(2, "lpn", "feminine")]
    roots, rots = bn_walk.translations[:FRAMES, 1], bn_walk.rotations[:FRAMES]

    def run(on_tick=None):
        out = []
        with Client(lb, timeout=30).crowd(chars, fps=30, reconnect_timeout=20) as crowd:
            for t in range(FRAMES):
                if t == STYLE_AT:
                    crowd.set_style("exhausted", characters=[0], transition_frames=20)
                reply = crowd.tick([0, 1, 2], np.tile(roots[t], (3, 1)), np.tile(rots[t], (3, 1, 1)))
                out.append(np.concatenate([reply.frame(i)[1].ravel() for i in range(3)]))
                if on_tick:
                    on_tick(t)
            return np.array(out), crowd.reconnects, crowd.last_reconnect

    want, _, _ = run()
    before = {s.port: s.metric("stylestream_frames_total") for s in servers}
    killed = []

    def kill_the_holder(t: int) -> None:
        if t + 1 == KILL_AFTER:
            holder = next(s for s in servers if s.metric("stylestream_frames_total") > before[s.port])
            holder.signal(signal.SIGKILL)
            holder.proc.wait(timeout=10)
            killed.append(holder)

    got, reconnects, event = run(kill_the_holder)
    assert killed and reconnects == 1
    # the ticks after the last store are sent again, and the style change if it came after it
    # (the store of tick KILL_AFTER - 1 may not have been written when the replica died)
    assert KILL_AFTER - 31 <= event.last_seq < KILL_AFTER and event.fresh == []
    assert event.replayed == KILL_AFTER - event.last_seq + (event.last_seq < STYLE_AT)
    for t, (g, w) in enumerate(zip(got, want, strict=True)):
        assert np.array_equal(g, w), t
