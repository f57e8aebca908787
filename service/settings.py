"""Service settings: the project's settings object plus what only the server needs.
Every field can be set as an environment variable STYLESTREAM_<FIELD> or in `.env`."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from pydantic import Field

from models.settings import REPO_ROOT, Settings


class ServiceSettings(Settings):
    host: str = Field(default="127.0.0.1", description="Interface to bind.")
    port: int = Field(default=8000, ge=1, le=65535)
    torch_threads: int = Field(default=1, ge=1, description="Intra-op threads; 1 leaves the other core to the event loop.")
    blas_threads: int = Field(default=1, ge=1, description="numpy BLAS threads (threadpoolctl), for the same reason.")
    batching: bool = Field(default=True, description="Cross-session batching; off = one step per frame (for benchmarks).")
    batch_wait_ms: float = Field(default=1.0, ge=0, le=50, description="How long a batch waits for more sessions' frames.")
    max_batch: int = Field(default=256, ge=1)
    max_sessions: int = Field(default=1024, ge=1)
    session_queue: int = Field(default=8, ge=1, description="Frames queued per session before the oldest are dropped.")
    idle_timeout_s: float = Field(default=60.0, gt=0, description="Sessions silent this long are closed and freed.")
    max_message_bytes: int = Field(default=256 * 1024, ge=1024, description="Largest WebSocket message accepted.")
    snapshot_every: int = Field(default=30, ge=1, description="Frames between session snapshots (for resume).")
    resume_ttl_s: float = Field(default=600.0, gt=0, description="How long a closed session can be resumed.")
    session_store: str = Field(default="memory", pattern=r"^(memory|(redis|rediss|unix)://.*)$",
                               description="Where snapshots live: 'memory' (this replica) or redis://host:port/db (shared).")
    drain_timeout_s: float = Field(default=15.0, gt=0, le=600,
                                   description="On SIGTERM: snapshot and close every session, then exit within this.")
    api_tokens: list[str] = Field(default_factory=list, description="When set, every request needs one (Bearer or ?token=).")
    styles_dir: Path = Field(default=REPO_ROOT / ".data" / "styles", description="Uploaded styles (clip, translator, metadata).")
    upload_max_bytes: int = Field(default=16 * 1024 * 1024, ge=1024, description="Largest style upload body accepted (413 above).")
    upload_min_frames: int = Field(default=60, ge=30, description="Shortest uploaded clip, in frames at 30 fps.")
    upload_max_frames: int = Field(default=9000, ge=60, description="Longest uploaded clip, in frames at 30 fps.")


@lru_cache
def get_service_settings() -> ServiceSettings:
    return ServiceSettings()
