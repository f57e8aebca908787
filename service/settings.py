"""Service settings: the project's settings object plus what only the server needs.
Every field can be set as an environment variable STYLESTREAM_<FIELD> or in `.env`."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field, model_validator

from models.settings import REPO_ROOT, Settings

from .background import BACKGROUND_CPUS, BACKGROUND_NICE

TOKEN_SHARE = 0.25  # of the server's sessions and characters, one token's by default


class TokenLimits(BaseModel):
    """One API token's own limits (`token_limits`); a field left out takes the default."""

    model_config = ConfigDict(extra="forbid")
    max_sessions: int | None = Field(default=None, ge=1)
    max_characters: int | None = Field(default=None, ge=1)
    requests_per_s: float | None = Field(default=None, gt=0, allow_inf_nan=False)
    burst_s: float | None = Field(default=None, gt=0, allow_inf_nan=False)
    upload_max_bytes: int | None = Field(default=None, ge=1024)


class ServiceSettings(Settings):
    host: str = Field(default="127.0.0.1", description="Interface to bind.")
    port: int = Field(default=8000, ge=1, le=65535)
    torch_threads: int = Field(
        default=1, ge=1, description="Intra-op threads; 1 leaves the other core to the event loop."
    )
    blas_threads: int = Field(default=1, ge=1, description="numpy BLAS threads (threadpoolctl), for the same reason.")
    batching: bool = Field(
        default=True, description="Cross-session batching; off = one step per frame (for benchmarks)."
    )
    core_pipelines: bool = Field(
        default=True,
        description="Also serve each method's published core alone (a session's `pipeline: core`); "
        "measured cost: ~0.3 s of start-up and ~35 MB beside the shipped pipelines (python -m clients.pipeline_cost).",
    )
    unseen_fade: bool = Field(
        default=True,
        description="End every shipped pipeline in the unseen-content fade (models/motion/novelty.py): input far from "
        "what a method trained on keeps its content instead of being styled. Off: the style is applied to every frame "
        "(docs/evaluation.md, 'faded', says how often it fades on each source).",
    )
    posture_calibration: bool = Field(
        default=True,
        description="Begin every shipped pipeline with the posture calibration (models/motion/calibration.py): a "
        "session whose first 1.5 s hold a joint outside the range of the model's own clips (another performer, "
        "another solve) has it turned into range before the model and back after. Off: frames reach the model as sent.",
    )
    batch_wait_ms: float = Field(
        default=1.0, ge=0, le=50, description="How long a batch waits for more sessions' frames."
    )
    direct_frames: bool = Field(
        default=True,
        description="Single-session binary frames taken straight from the WebSocket protocol and "
        "answered from the batch step's callback, without the per-message ASGI path "
        "(`service.transport`); off = every message through ASGI receive/send (for benchmarks).",
    )
    step_inline_max_ms: float = Field(
        default=5.0,
        ge=0,
        description="Model steps predicted shorter than this run on "
        "the event loop (no thread hop); longer ones on the model thread. 0: always the thread.",
    )
    workers: int = Field(
        default=1,
        ge=1,
        le=64,
        description="Server processes sharing the port (SO_REUSEPORT), each "
        "with its own batcher; resume across them needs a shared session_store (redis://).",
    )
    max_batch: int = Field(default=256, ge=1)
    max_sessions: int = Field(default=1024, ge=1)
    max_characters: int = Field(
        default=16384, ge=1, description="Characters in all crowd connections together (protocol v1.1)."
    )
    session_queue: int = Field(default=8, ge=1, description="Frames queued per session before the oldest are dropped.")
    idle_timeout_s: float = Field(default=60.0, gt=0, description="Sessions silent this long are closed and freed.")
    max_message_bytes: int = Field(default=256 * 1024, ge=1024, description="Largest WebSocket message accepted.")
    header_timeout_s: float = Field(
        default=10.0,
        gt=0,
        le=600,
        description="A connection whose request headers take longer (this to 1.5x it, spread per "
        "connection so a burst is not dropped in one go) is dropped.",
    )
    send_timeout_s: float = Field(
        default=10.0,
        gt=0,
        le=600,
        description="A WebSocket client that reads nothing this long while replies wait is disconnected "
        "(its session kept for resume).",
    )
    ping_interval_s: float = Field(
        default=20.0, gt=0, le=600, description="WebSocket keepalive pings; a peer silent to one this long is dropped."
    )
    background_nice: int = Field(
        default=BACKGROUND_NICE,
        ge=0,
        le=19,
        description="Niceness of work no frame waits for (style building, upload decoding, fine-tunes, file "
        "writes). Higher keeps it further from the streams, but also behind every other busy process: at 19 an "
        "upload beside a few busy processes barely runs.",
    )
    background_cpus: int = Field(
        default=BACKGROUND_CPUS,
        ge=0,
        le=4096,
        description="How many CPUs that background work may use (the last of those the process may use; Linux): "
        "0 = all but one, leaving the streams a core no upload competes for.",
    )
    gil_switch_interval_s: float = Field(
        default=0.0005,
        gt=0,
        le=0.1,
        description="How long a Python thread may hold the GIL while another waits for it (sys.setswitchinterval; "
        "Python's default is 0.005). Style building and fine-tunes run on background threads: at the default "
        "the event loop waited up to 5 ms behind them, each a stream's late frame.",
    )
    max_connections: int = Field(
        default=4096, ge=1, description="Open connections and requests at once; above it 503 (uvicorn)."
    )
    max_messages_per_s: float = Field(
        default=10000.0,
        gt=0,
        allow_inf_nan=False,
        description="Per connection: WebSocket messages per second (bursts of a second's worth); beyond it "
        "they are dropped with a typed error, and a second's worth more closes the connection.",
    )
    connection_loop_share: float = Field(
        default=0.25,
        ge=0,
        le=1,
        description="Per connection: the share of the event loop its messages may take to handle (parsing "
        "them, answering its frames) while it sends faster than they are handled; past it its receiver pauses "
        "and the rest waits in its socket. A real-time stream takes ~1 %. 0 or 1: no limit.",
    )
    max_controls_per_s: float = Field(
        default=20.0,
        gt=0,
        allow_inf_nan=False,
        description="Per connection: style and reset messages per second (each costs a model reset or a "
        "reply), counted like max_messages_per_s.",
    )
    snapshot_every: int = Field(default=30, ge=1, description="Frames between session snapshots (for resume).")
    resume_ttl_s: float = Field(default=600.0, gt=0, description="How long a closed session can be resumed.")
    session_store: str = Field(
        default="memory",
        pattern=r"^(memory|(redis|rediss|unix)://.*)$",
        description="Where snapshots live: 'memory' (this replica) or redis://host:port/db (shared).",
    )
    drain_timeout_s: float = Field(
        default=15.0, gt=0, le=600, description="On SIGTERM: snapshot and close every session, then exit within this."
    )
    api_tokens: list[str] = Field(
        default_factory=list, description="When set, every request needs one (Bearer or ?token=)."
    )
    token_max_sessions: int | None = Field(
        default=None,
        ge=1,
        description="Per token (per client address without tokens): concurrent streaming sessions and "
        "crowd connections (1013 above); by default a quarter of max_sessions, so one caller cannot "
        "take every session.",
    )
    token_max_characters: int | None = Field(
        default=None,
        ge=1,
        description="Per token (per client address without tokens): characters in its crowds together "
        "(too_many_characters above); by default a quarter of max_characters, so one caller cannot "
        "take every character.",
    )
    token_sessions_per_s: float = Field(
        default=50.0,
        gt=0,
        allow_inf_nan=False,
        description="Per token (per client address without tokens): new streaming sessions per second, "
        "in bursts of token_max_sessions (1013 above): churn cannot fill the snapshot store.",
    )
    flood_cooldown_s: float = Field(
        default=10.0,
        ge=0,
        le=3600,
        allow_inf_nan=False,
        description="Per token (per client address without tokens): after one of its connections is closed "
        "for flooding (4429), its WebSocket handshakes are refused this long (HTTP 429 rate_limited), so a "
        "flood that reconnects costs the server one connection's burst; its open sessions go on. 0: off.",
    )
    token_max_stored_sessions: int = Field(
        default=256,
        ge=1,
        description="Per token (per client address without tokens): closed sessions kept for resume; "
        "beyond it that caller's oldest is forgotten (never another caller's).",
    )
    admin_tokens: list[str] = Field(
        default_factory=list, description="API tokens that see and manage every tenant's uploaded styles."
    )
    token_requests_per_s: float = Field(
        default=20.0,
        gt=0,
        allow_inf_nan=False,
        description="Per token: REST requests per second, a token bucket (429 above).",
    )
    token_burst_s: float = Field(
        default=2.0,
        gt=0,
        allow_inf_nan=False,
        description="Per token: bursts of up to this many seconds' worth of requests pass at once (the bucket's size).",
    )
    token_limits: dict[str, TokenLimits] = Field(
        default_factory=dict,
        description="Per-token overrides, JSON: "
        '{"tok": {"max_sessions": 4, "requests_per_s": 5, "upload_max_bytes": 1000000}}.',
    )
    styles_dir: Path = Field(
        default=REPO_ROOT / ".data" / "styles", description="Uploaded styles (clip, translator, metadata)."
    )
    styles_refresh_s: float = Field(
        default=0.0,
        ge=0,
        le=3600,
        allow_inf_nan=False,
        description="Replicas sharing "
        "one styles_dir: rescan it this often (seconds) for styles the others added, "
        "fine-tuned or deleted; 0 = the folder is this server's own.",
    )
    upload_max_bytes: int = Field(
        default=16 * 1024 * 1024, ge=1024, description="Largest style upload body accepted (413 above)."
    )
    upload_min_frames: int = Field(default=60, ge=30, description="Shortest uploaded clip, in frames at 30 fps.")
    upload_max_frames: int = Field(default=9000, ge=60, description="Longest uploaded clip, in frames at 30 fps.")
    upload_min_fps: float = Field(
        default=10.0, gt=0, le=1000, allow_inf_nan=False, description="Lowest frame rate of an uploaded clip."
    )
    upload_max_fps: float = Field(
        default=480.0, gt=0, le=10000, allow_inf_nan=False, description="Highest frame rate of an uploaded clip."
    )
    upload_decode_cpu_s: float = Field(
        default=20.0,
        gt=0,
        le=600,
        description="CPU seconds decoding, retargeting and resampling an upload (in a child process) may take: "
        "422 clip_too_slow above. CPU, not wall-clock time: a busy machine slows an upload, it does not refuse it.",
    )
    upload_decode_wall_s: float = Field(
        default=120.0,
        gt=0,
        le=3600,
        description="How long an upload waits for its decoding however busy the machine: 503 server_busy after.",
    )
    upload_decode_memory_mb: int = Field(
        default=1024, ge=8, description="Memory a child process decoding an upload may take beyond its start."
    )
    upload_decoders: int = Field(default=2, ge=1, le=64, description="Uploads decoded at once; more wait their turn.")
    lpn_fine_tune_steps: int = Field(
        default=300,
        ge=1,
        le=5000,
        description="Adam steps of an LPN-FiLM style's "
        "fine-tune job (FiLM generator on the uploaded clip, network frozen; ~20-30 s at 300).",
    )

    @model_validator(mode="after")
    def _workers_share_sessions(self) -> ServiceSettings:
        if self.workers > 1 and self.session_store == "memory":  # a resume would land on a worker without its snapshot
            raise ValueError(
                f"workers={self.workers} needs a shared session_store (redis://host:port/db): with the "
                "in-memory store a client resuming on another worker than its first finds no session"
            )
        return self

    @property
    def token_sessions(self) -> int:
        """One token's sessions by default: `token_max_sessions`, else TOKEN_SHARE of the server's."""
        return self.token_max_sessions or max(1, int(self.max_sessions * TOKEN_SHARE))

    @property
    def token_characters(self) -> int:
        """One token's crowd characters by default: `token_max_characters`, else TOKEN_SHARE of
        the server's (at the server's own maximum, the old default, one token's crowd held all
        16,384 characters and stalled every stream)."""
        return self.token_max_characters or max(1, int(self.max_characters * TOKEN_SHARE))

    @model_validator(mode="after")
    def _admins_are_tokens(self) -> ServiceSettings:
        if not set(self.admin_tokens) <= set(self.api_tokens):
            raise ValueError("admin_tokens must also be listed in api_tokens")
        return self

    @model_validator(mode="after")
    def _limits_name_known_tokens(self) -> ServiceSettings:
        unknown = set(self.token_limits) - set(self.api_tokens)
        if unknown:  # a typo here would silently give that client the defaults
            raise ValueError(f"token_limits names {len(unknown)} token(s) that are not in api_tokens")
        return self


@lru_cache
def get_service_settings() -> ServiceSettings:
    return ServiceSettings()
