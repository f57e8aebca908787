"""Session stores (memory, real Redis), the background snapshot writer, and live sessions that
keep streaming while the store is down."""

from __future__ import annotations

import asyncio
import dataclasses
import time

import numpy as np
import pytest

from clients.loadtest import free_port
from clients.sdk import AsyncClient, Client, _pack
from models.registry import load_models
from models.settings import get_settings
from service.metrics import Metrics
from service.session_store import (
    KEY_PREFIX,
    MemoryStore,
    RedisStore,
    SessionStore,
    SnapshotWriter,
    StoreUnavailable,
    create_store,
)
from service.sessions import Snapshot

from .cluster import redis_server, require
from .live_server import live_server


def snapshot(token: str = "tok", last_seq: int | None = 7) -> Snapshot:
    state = {
        "h": np.random.default_rng(0).normal(size=(1, 2, 32)).astype(np.float32),
        "started": np.array([True]),
        "frame": np.array([41], dtype=np.int64),
        "yaw": np.array([0.1 + 1e-17], dtype=np.float64),
    }
    held = {
        "root": np.array([1.0, 93.2, -4.5]),
        "rotations": np.tile([0.0, 0.0, 0.0, 1.0], (22, 1)),
        "input_root": np.array([0.5, 93.0, -4.0]),
    }
    return Snapshot(
        session_id="s1",
        token=token,
        model="lti",
        skeleton="bandai-namco",
        bvh_header=None,
        fps=30.0,
        encoding="binary",
        weights={"elderly": 0.25, "active": 0.75},
        target={"elderly": 1.0},
        transition_left=12,
        last_seq=last_seq,
        clock=0.5,
        held=held,
        state=state,
        saved_at=time.time(),
    )


def assert_same(a: Snapshot, b: Snapshot) -> None:
    arrays = ("state", "held", "last_output")
    assert {k: v for k, v in a.__dict__.items() if k not in arrays} == {
        k: v for k, v in b.__dict__.items() if k not in arrays
    }
    for name in arrays:
        x, y = getattr(a, name), getattr(b, name)
        assert x.keys() == y.keys()
        for key in x:
            assert x[key].dtype == y[key].dtype and x[key].shape == y[key].shape
            assert x[key].tobytes() == y[key].tobytes()  # bit for bit


def test_a_stored_snapshot_is_exact_for_every_dtype():
    snap = snapshot()
    assert_same(Snapshot.from_bytes(snap.to_bytes()), snap)
    odd = dataclasses.replace(
        snap,
        bvh_header='HIERARCHY\nROOT "Hips"\n{\n',  # newlines and quotes in the text fields
        last_output={"root": np.zeros((1, 3)), "none": np.zeros((0, 4), np.float32), "scalar": np.float64(2.5)},
        state={**snap.state, "big_endian": np.arange(3, dtype=">i4")},
    )
    assert_same(Snapshot.from_bytes(odd.to_bytes()), odd)


def test_a_snapshot_stored_as_json_by_an_earlier_replica_is_still_read():
    """A rolling upgrade: the new replicas resume what the old ones stored."""
    snap = snapshot()
    assert_same(Snapshot.from_bytes(snap.to_json().encode()), snap)


def test_what_is_not_a_snapshot_is_refused():
    data = snapshot().to_bytes()
    for bad in (b"PNG", data[:-1], data + b"x"):
        with pytest.raises(ValueError):
            Snapshot.from_bytes(bad)


def test_the_setting_picks_the_store():
    assert isinstance(create_store("memory", 60), MemoryStore)
    assert isinstance(create_store("redis://127.0.0.1:6379/0", 60), RedisStore)
    with pytest.raises(ValueError, match="memory"):
        create_store("postgres://x", 60)


@pytest.fixture(scope="module")
def redis_url(tmp_path_factory):
    require("redis-server")
    with redis_server(tmp_path_factory.mktemp("redis")) as url:
        yield url


def on_store(url: str, ttl_s: float, body) -> None:
    """Run the coroutine function `body(store)` on a fresh store of `url`, closed afterwards."""

    async def run():
        store = create_store(url, ttl_s=ttl_s)
        try:
            await body(store)
        finally:
            await store.close()

    asyncio.run(run())


@pytest.mark.parametrize("kind", ["memory", "redis"])
def test_stores_keep_replace_delete_and_expire_snapshots(kind, request):
    url = request.getfixturevalue("redis_url") if kind == "redis" else "memory"

    async def body(store):
        newest = snapshot("a", 3)
        await store.write({"a": snapshot("a", 1), "b": snapshot("b", 2)}, [])
        await store.write({"a": newest}, ["b"])
        assert_same(await store.get("a"), newest)
        assert await store.get("b") is None and await store.get("never") is None
        await asyncio.sleep(0.7)
        assert await store.get("a") is None  # expired after resume_ttl_s

    on_store(url, 0.5, body)


def test_a_batch_larger_than_one_pipeline_is_written_whole(redis_url):
    """A crowd's snapshots go to Redis `WRITE_CHUNK` at a time: every one arrives, deletes too."""
    from service.session_store import WRITE_CHUNK

    async def body(store):
        tokens = [f"crowd-{k}" for k in range(2 * WRITE_CHUNK + 5)]
        await store.write({t: snapshot(t) for t in tokens}, [])
        await store.write({}, tokens[: WRITE_CHUNK + 1])
        kept = [await store.get(t) for t in tokens]
        assert [s is None for s in kept] == [True] * (WRITE_CHUNK + 1) + [False] * (WRITE_CHUNK + 4)
        assert [s.token for s in kept[WRITE_CHUNK + 1 :]] == tokens[WRITE_CHUNK + 1 :]

    on_store(redis_url, 60, body)


def test_an_unreadable_value_in_redis_is_an_unknown_snapshot_not_a_crash(redis_url):
    """A damaged value, or another program's under our key: the resume gets `unknown_resume_token`."""

    async def body(store):
        kept = snapshot("ok")
        good = kept.to_bytes()
        for token, value in (("cut", good[:-3]), ("foreign", b"PNG..."), ("json", b'{"a": 1}')):
            await store.redis.set(KEY_PREFIX + token, value)
            assert await store.get(token) is None
        await store.redis.set(KEY_PREFIX + "ok", good)
        assert_same(await store.get("ok"), kept)

    on_store(redis_url, 60, body)


def test_an_unreachable_redis_is_a_typed_error_within_about_a_second():
    async def run():
        store = RedisStore(f"redis://127.0.0.1:{free_port()}/0", ttl_s=60)
        t0 = time.monotonic()
        with pytest.raises(StoreUnavailable):
            await store.get("tok")
        with pytest.raises(StoreUnavailable):
            await store.write({"tok": snapshot()}, [])
        await store.close()
        return time.monotonic() - t0

    assert asyncio.run(run()) < 3


class FlakyStore(MemoryStore):
    """A memory store that fails its first `failures` writes, recording every batch."""

    def __init__(self, failures: int) -> None:
        super().__init__(ttl_s=60)
        self.failures, self.batches = failures, []

    async def write(self, puts, deletes) -> None:
        self.batches.append((sorted(puts), sorted(deletes)))
        if self.failures:
            self.failures -= 1
            raise StoreUnavailable("down")
        await super().write(puts, deletes)


def run_writer(store: SessionStore, body):
    async def run():
        writer = SnapshotWriter(store, Metrics(), retry_s=0.05)
        writer.start()
        try:
            return await body(writer)
        finally:
            await writer.stop()

    return asyncio.run(run())


def test_the_writer_keeps_the_newest_snapshot_per_session_and_acknowledges_it():
    store = FlakyStore(failures=0)
    acked = []

    async def body(writer: SnapshotWriter):
        for seq in (29, 59):
            writer.put(snapshot("a", seq), on_saved=lambda s: acked.append(s.last_seq))
        writer.put(snapshot("b", 5))
        assert (await writer.get("a")).last_seq == 59  # queued entries are seen before the store
        assert await writer.flush(2)
        writer.delete("b")
        assert await writer.get("b") is None
        assert await writer.flush(2)
        return (await store.get("a")).last_seq, await store.get("b")

    assert run_writer(store, body) == (59, None)
    assert store.batches == [(["a", "b"], []), ([], ["b"])]  # one round trip per batch
    assert acked == [59]


def test_a_store_outage_is_counted_retried_and_recovers():
    store = FlakyStore(failures=3)
    metrics_holder = {}

    async def body(writer: SnapshotWriter):
        metrics_holder["m"] = writer.metrics
        writer.put(snapshot("a", 29))
        assert not await writer.flush(0.08)  # still failing
        writer.put(snapshot("a", 59))  # newer than the one being retried: it wins
        assert await writer.flush(2)
        return (await store.get("a")).last_seq

    assert run_writer(store, body) == 59
    assert metrics_holder["m"].snapshot_failures._value.get() == 3
    assert metrics_holder["m"].snapshots._value.get() == 1


def test_sessions_keep_streaming_and_resume_on_their_replica_while_redis_is_down(bn_walk):
    """No Redis at the configured address: every snapshot write fails (counted on /metrics),
    frames keep coming, and a dropped connection still resumes exactly here (the writer holds
    the unsaved snapshot)."""
    import httpx

    root, rot = bn_walk.translations[:40, 1], bn_walk.rotations[:40]
    models = load_models(get_settings().weights_dir)
    with live_server(models, session_store=f"redis://127.0.0.1:{free_port()}/0", snapshot_every=5) as (base, _):
        with Client(base).session(model="lti", style="elderly") as session:
            whole = [session.stylise(root[t], rot[t]).rotations for t in range(40)]
        with Client(base).session(model="lti", style="elderly") as session:
            first = [session.stylise(root[t], rot[t]).rotations for t in range(20)]
            session.ws.close()
            rest = [session.stylise(root[t], rot[t]).rotations for t in range(20, 40)]
            assert session.reconnects == 1
        failures = [
            line
            for line in httpx.get(f"{base}/metrics").text.splitlines()
            if line.startswith("stylestream_snapshot_failures_total")
        ]
    assert float(failures[0].split()[-1]) > 0
    np.testing.assert_allclose(np.array(first + rest), np.array(whole), atol=1e-6)


def test_a_reply_lost_with_the_connection_comes_back_with_the_resumed_session(bn_walk):
    """The server stylised frame 10 and saved it in the snapshot, but its reply never reached
    the client: resuming hands the saved reply over, and the stream continues unchanged."""
    root, rot = bn_walk.translations[:20, 1], bn_walk.rotations[:20]
    models = load_models(get_settings().weights_dir)
    with live_server(models) as (base, _):
        with Client(base).session(model="lti", style="elderly") as session:
            whole = [session.stylise(root[t], rot[t]) for t in range(20)]
        with Client(base).session(model="lti", style="elderly") as session:
            got = [session.stylise(root[t], rot[t]) for t in range(10)]
            session.ws.send(_pack(10, root[10], rot[10]))
            assert isinstance(session.ws.recv(timeout=10), bytes)  # processed; the reply is "lost"
            session.ws.close()
            got += [session.stylise(root[t], rot[t]) for t in range(10, 20)]
            assert session.reconnects == 1 and session.info["last_seq"] == 10
    assert [f.seq for f in got] == list(range(20))
    np.testing.assert_array_equal(np.array([f.rotations for f in got]), np.array([f.rotations for f in whole]))
    np.testing.assert_array_equal(np.array([f.root for f in got]), np.array([f.root for f in whole]))


def test_the_async_sdk_resumes_exactly_too(bn_walk):
    """AsyncSession: the socket drops mid-stream, during a style transition; the resumed outputs
    equal an uninterrupted run's."""
    root, rot = bn_walk.translations[:24, 1], bn_walk.rotations[:24]
    models = load_models(get_settings().weights_dir)

    async def run(base: str, drop: bool):
        async with AsyncClient(base).session(model="lti", style="elderly") as session:
            out = [await session.stylise(root[t], rot[t]) for t in range(8)]
            await session.set_style("exhausted", transition_frames=6)
            out += [await session.stylise(root[t], rot[t]) for t in range(8, 12)]
            if drop:
                await session.ws.close()
            out += [await session.stylise(root[t], rot[t]) for t in range(12, 24)]
            return np.array([f.rotations for f in out]), session.reconnects

    with live_server(models, snapshot_every=5) as (base, _):
        want, _ = asyncio.run(run(base, drop=False))
        got, reconnects = asyncio.run(run(base, drop=True))
    assert reconnects == 1
    np.testing.assert_array_equal(got, want)


class HeldStore(MemoryStore):
    """A store whose writes wait until released, as a shared store's round trip does."""

    def __init__(self) -> None:
        super().__init__(ttl_s=60)
        self.writing, self.release = asyncio.Event(), asyncio.Event()

    async def write(self, puts: dict[str, Snapshot], deletes: list[str]) -> None:
        self.writing.set()
        await self.release.wait()
        await super().write(puts, deletes)


def test_a_snapshot_being_written_is_seen_by_a_resume():
    """Taken from the queue but not yet in the store, a snapshot is still the writer's to give:
    a client resuming at that moment was told its token was unknown."""
    store = HeldStore()

    async def body(writer: SnapshotWriter):
        writer.put(snapshot("a", 29))
        await asyncio.wait_for(store.writing.wait(), 2)
        seen = await writer.get("a")
        store.release.set()
        assert await writer.flush(2)
        return None if seen is None else seen.last_seq, (await writer.get("a")).last_seq

    assert run_writer(store, body) == (29, 29)
