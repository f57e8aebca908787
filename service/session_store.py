"""Where session snapshots live between connections, and how they get there without slowing
the stream.

`SessionStore` is the interface (async, keyed by resume token, entries expire after
`resume_ttl_s`): `MemoryStore` for one replica, `RedisStore` (`redis.asyncio`) for replicas
sharing sessions. `create_store` picks one from `STYLESTREAM_SESSION_STORE`.

Sessions never wait on the store: `SnapshotWriter` keeps the newest snapshot per token and one
background task writes whatever has gathered in a single pipelined round trip. An unreachable
store is logged and counted (`stylestream_snapshot_failures_total`); its snapshots stay queued
(newest per session) and are retried, and the sessions keep streaming.
"""

from __future__ import annotations

import asyncio
import logging
import time
from abc import ABC, abstractmethod
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

from .metrics import Metrics
from .sessions import Snapshot

log = logging.getLogger(__name__)

KEY_PREFIX = "stylestream:snapshot:"
CLAIM_PREFIX = "stylestream:resuming:"
WRITE_CHUNK = 64  # snapshots per Redis pipeline (`RedisStore.write`)
# how long a resume's claim on its token holds the token against other replicas' resumes: two
# resumes at once on two replicas both opened (each replica's in-use check sees only its own);
# it expires rather than being released, so a replica killed right after a resume delays a
# resume elsewhere by at most this (the SDK retries `session_in_use`)
CLAIM_S = 5.0


class StoreUnavailable(RuntimeError):
    """The session store could not be reached (or answered with an error)."""


class SessionStore(ABC):
    """Snapshots keyed by resume token, each kept for `ttl_s` after its last write."""

    def __init__(self, ttl_s: float) -> None:
        self.ttl_s = ttl_s

    @abstractmethod
    async def get(self, token: str) -> Snapshot | None:
        """The snapshot for `token`, None if unknown or expired; StoreUnavailable on failure."""

    async def claim(self, token: str, holder: str) -> bool:
        """Take `token` for a resume by `holder` (a replica) for CLAIM_S; False if another replica
        took it within that time. One process's own resumes are checked by its runtime: a store
        only it uses has nothing to add."""
        return True

    @abstractmethod
    async def write(self, puts: dict[str, Snapshot], deletes: list[str]) -> None:
        """Store `puts` and remove `deletes` in one go; StoreUnavailable on failure."""

    async def close(self) -> None:  # noqa: B027 - optional: a store without connections has nothing to release
        """Release connections."""


class MemoryStore(SessionStore):
    """This process only, oldest first so expiry is cheap. Snapshots are held as they are
    (model states are never modified in place)."""

    def __init__(self, ttl_s: float) -> None:
        super().__init__(ttl_s)
        self._data: OrderedDict[str, tuple[float, Snapshot]] = OrderedDict()

    async def get(self, token: str) -> Snapshot | None:
        self._expire()
        entry = self._data.get(token)
        return entry[1] if entry else None

    async def write(self, puts: dict[str, Snapshot], deletes: list[str]) -> None:
        now = time.monotonic()
        for token, snap in puts.items():
            self._data[token] = (now, snap)
            self._data.move_to_end(token)
        for token in deletes:
            self._data.pop(token, None)
        self._expire()

    def _expire(self) -> None:
        limit = time.monotonic() - self.ttl_s
        while self._data and next(iter(self._data.values()))[0] < limit:
            self._data.popitem(last=False)


class RedisStore(SessionStore):
    """Shared by every replica pointing at the same Redis: `SET key json PX ttl` per snapshot
    (`Snapshot.to_bytes`), pipelined. Short socket timeouts and a single retry, so an outage costs
    a failed write within about a second rather than stalling the writer."""

    def __init__(self, url: str, ttl_s: float, timeout_s: float = 1.0) -> None:
        from redis.asyncio import Redis
        from redis.asyncio.retry import Retry
        from redis.backoff import NoBackoff

        super().__init__(ttl_s)
        self.url = url
        self.redis = Redis.from_url(
            url, socket_timeout=timeout_s, socket_connect_timeout=timeout_s, retry=Retry(NoBackoff(), 1)
        )

    async def get(self, token: str) -> Snapshot | None:
        from redis.exceptions import RedisError

        try:
            data = await self.redis.get(KEY_PREFIX + token)
        except (RedisError, OSError) as exc:
            raise StoreUnavailable(f"session store {self.url}: {exc}") from exc
        if data is None:
            return None
        try:
            return Snapshot.from_bytes(data)
        except (ValueError, TypeError, KeyError) as exc:  # damaged, or another program's value under our key
            log.warning("unreadable session snapshot under token %s…, taken as unknown: %s", token[:8], exc)
            return None

    async def claim(self, token: str, holder: str) -> bool:
        """`SET NX` of a claim key: of two replicas resuming one token at once, one gets it."""
        from redis.exceptions import RedisError

        try:
            taken = await self.redis.set(CLAIM_PREFIX + token, holder, nx=True, px=int(CLAIM_S * 1000))
            return bool(taken) or (await self.redis.get(CLAIM_PREFIX + token)) == holder.encode()
        except (RedisError, OSError) as exc:
            raise StoreUnavailable(f"session store {self.url}: {exc}") from exc

    async def write(self, puts: dict[str, Snapshot], deletes: list[str]) -> None:
        from redis.exceptions import RedisError

        ttl_ms = int(self.ttl_s * 1000)
        ops: list[tuple[str, Snapshot | None]] = [*puts.items(), *((token, None) for token in deletes)]
        try:
            # a pipeline per WRITE_CHUNK snapshots: each is encoded on the event loop, and a
            # crowd's thousands at once would hold its streams for tens of milliseconds
            for first in range(0, len(ops), WRITE_CHUNK):
                async with self.redis.pipeline(transaction=False) as pipe:
                    for token, snap in ops[first : first + WRITE_CHUNK]:
                        if snap is None:
                            pipe.delete(KEY_PREFIX + token)
                        else:
                            pipe.set(KEY_PREFIX + token, snap.to_bytes(), px=ttl_ms)
                    await pipe.execute()
        except (RedisError, OSError) as exc:
            raise StoreUnavailable(f"session store {self.url}: {exc}") from exc

    async def close(self) -> None:
        await self.redis.aclose()


def create_store(spec: str, ttl_s: float) -> SessionStore:
    """`memory`, or a Redis URL (`redis://host:port/db`, `rediss://…`, `unix://…`)."""
    if spec == "memory":
        return MemoryStore(ttl_s)
    if spec.startswith(("redis://", "rediss://", "unix://")):
        return RedisStore(spec, ttl_s)
    raise ValueError(f"session store must be 'memory' or a redis:// URL, got {spec!r}")


SavedCallback = Callable[[Snapshot], None]


@dataclass
class _Pending:
    snapshot: Snapshot | None  # None: delete (the session ended)
    on_saved: SavedCallback | None
    queued_at: float


class SnapshotWriter:
    """Writes snapshots to the store in the background, newest per session, in batches.

    `put` and `delete` return at once. `get` sees queued entries first, so a client resuming on
    the replica it just left always gets its latest snapshot. `on_saved` runs (on the event loop)
    once a snapshot is in the store: the connection tells its client which frames are safe."""

    def __init__(self, store: SessionStore, metrics: Metrics, retry_s: float = 1.0) -> None:
        self.store, self.metrics, self.retry_s = store, metrics, retry_s
        self._pending: dict[str, _Pending] = {}
        self._writing: dict[str, _Pending] = {}  # the batch the store is writing now
        self._wake = asyncio.Event()
        self._idle = asyncio.Event()
        self._idle.set()
        self._task: asyncio.Task | None = None
        self._failing = False

    def start(self) -> None:
        self._task = asyncio.get_running_loop().create_task(self._run(), name="snapshot-writer")

    async def stop(self, timeout_s: float = 2.0) -> None:
        """Write what is queued (within `timeout_s`), then close the store."""
        await self.flush(timeout_s)
        if self._task:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)
        await self.store.close()

    def put(self, snap: Snapshot, on_saved: SavedCallback | None = None) -> None:
        self._queue(snap.token, _Pending(snap, on_saved, time.monotonic()))

    def delete(self, token: str) -> None:
        self._queue(token, _Pending(None, None, time.monotonic()))

    def _queue(self, token: str, entry: _Pending) -> None:
        self._pending[token] = entry
        self._idle.clear()
        self._wake.set()

    async def get(self, token: str) -> Snapshot | None:
        # the batch being written too: between taking it from the queue and the store's answer, a
        # shared store (redis) did not hold it yet, and a client resuming at once was told the
        # token was unknown
        entry = self._pending.get(token)
        if entry is None:
            entry = self._writing.get(token)
        if entry is not None:
            return entry.snapshot
        return await self.store.get(token)

    async def claim(self, token: str, holder: str) -> bool:
        return await self.store.claim(token, holder)

    async def flush(self, timeout_s: float) -> bool:
        """Wait until everything queued so far is written; False if that took over `timeout_s`
        (the store is down or slow)."""
        try:
            await asyncio.wait_for(self._idle.wait(), timeout_s)
            return True
        except TimeoutError:
            return False

    async def _run(self) -> None:
        while True:
            if not self._pending:
                self._idle.set()
                self._wake.clear()
                await self._wake.wait()
                continue
            batch, self._pending = self._pending, {}
            self._writing = batch
            puts = {t: e.snapshot for t, e in batch.items() if e.snapshot is not None}
            deletes = [t for t, e in batch.items() if e.snapshot is None]
            t0 = time.perf_counter()
            try:
                await self.store.write(puts, deletes)
            except StoreUnavailable as exc:
                self._writing = {}
                self.metrics.snapshot_failures.inc(len(batch))
                if not self._failing:
                    log.error("snapshots not saved, retrying every %.1f s: %s", self.retry_s, exc)
                self._failing = True
                self._requeue(batch)
                await asyncio.sleep(self.retry_s)
                continue
            self._writing = {}
            if self._failing:
                log.warning("session store reachable again")
                self._failing = False
            self.metrics.snapshot_seconds.observe(time.perf_counter() - t0)
            self.metrics.snapshots.inc(len(puts))
            for entry in batch.values():
                if entry.on_saved is not None and entry.snapshot is not None:
                    try:
                        entry.on_saved(entry.snapshot)
                    except Exception:
                        log.exception("snapshot callback failed")

    def _requeue(self, batch: dict[str, _Pending]) -> None:
        """Put a failed batch back, unless newer entries came meanwhile; entries older than the
        store's TTL are given up (they would have expired anyway)."""
        limit = time.monotonic() - self.store.ttl_s
        for token, entry in batch.items():
            if token not in self._pending and entry.queued_at >= limit:
                self._pending[token] = entry
