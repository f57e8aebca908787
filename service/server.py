"""Running the app under uvicorn with a graceful drain on SIGTERM (`stylestream serve`, the image),
its startup heap frozen out of the garbage collector (`DrainingServer.startup`).

Plain uvicorn answers SIGTERM by closing its listeners and waiting for open connections to end,
which for streaming sessions means until the client leaves or the orchestrator kills the
process: sessions lose whatever came after their last periodic snapshot. `DrainingServer`
drains first (`Runtime.drain`: readyz turns 503, new sessions are refused with 1012, every
session is stopped, snapshotted to the store and closed with 1012 and its resume token) and only
then lets uvicorn shut down, all within `drain_timeout_s`. A second signal skips the drain.
"""

from __future__ import annotations

import asyncio
import gc
import logging
import signal
import sys
import time
from types import FrameType

import uvicorn
from fastapi import FastAPI

from .app import create_app
from .background import placement, set_background
from .logs import configure_logging
from .runtime import Runtime
from .settings import ServiceSettings
from .transport import uvicorn_config

log = logging.getLogger("uvicorn.error")  # uvicorn's own lifecycle log, so drains show beside it


class DrainingServer(uvicorn.Server):
    def __init__(self, config: uvicorn.Config, app: FastAPI, drain_timeout_s: float) -> None:
        super().__init__(config)
        self.app, self.drain_timeout_s = app, drain_timeout_s
        self._loop: asyncio.AbstractEventLoop | None = None
        self._drain_task: asyncio.Task | None = None

    async def serve(self, sockets=None) -> None:
        self._loop = asyncio.get_running_loop()
        await super().serve(sockets)

    async def startup(self, sockets=None) -> None:
        """uvicorn's startup (the app's lifespan: models loaded and warmed), then the heap it
        built frozen out of the cyclic garbage collector. Why: torch, the models, numba and
        pydantic leave a few hundred thousand objects that live as long as the process, and every
        full collection walked them all: 100-130 ms pauses every few seconds under a 2,000
        character crowd, each one every stream's worst frame. Frozen, they are never walked."""
        await super().startup(sockets)
        if self.started:
            gc.collect()
            gc.freeze()
            log.info("froze %d startup objects out of the garbage collector", gc.get_freeze_count())

    def handle_exit(self, sig: int, frame: FrameType | None) -> None:
        """Signal handler (main thread, between bytecodes of the loop): schedule the drain."""
        runtime: Runtime | None = self.app.state.runtime  # None until the app has started
        if (
            self._drain_task is not None
            or runtime is None
            or self._loop is None
            or sig not in (signal.SIGTERM, signal.SIGINT)
        ):
            super().handle_exit(sig, frame)  # second signal, or nothing to drain: uvicorn's own way
            return
        self._loop.call_soon_threadsafe(self._start_drain, self._loop, sig, runtime)

    def _start_drain(self, loop: asyncio.AbstractEventLoop, sig: int, runtime: Runtime) -> None:
        if self._drain_task is not None:
            return
        log.info("draining %d session(s), at most %.1f s", len(runtime.connections), self.drain_timeout_s)
        loop.call_later(self.drain_timeout_s, self._give_up)
        self._drain_task = loop.create_task(self._drain(sig, runtime))

    async def _drain(self, sig: int, runtime: Runtime) -> None:
        t0 = time.perf_counter()
        try:
            await runtime.drain(0.7 * self.drain_timeout_s)
        except Exception:
            log.exception("drain failed")
        log.info("drained in %.3f s", time.perf_counter() - t0)
        super().handle_exit(sig, None)  # now uvicorn closes listeners and waits out what is left

    def _give_up(self) -> None:
        if not self.force_exit:
            log.error("drain timeout of %.1f s reached: exiting", self.drain_timeout_s)
            self.should_exit = self.force_exit = True


def serve(settings: ServiceSettings, log_level: str = "info") -> None:
    """One server, or `settings.workers` of them on one port (`service.workers`)."""
    if settings.workers > 1:
        from .workers import serve_workers

        serve_workers(settings, log_level)
    else:
        serve_once(settings, log_level)


def tune_interpreter(settings: ServiceSettings) -> None:
    """Process-wide settings for a serving process: where background work runs (niceness and
    CPUs, `service.background`), and the GIL switch interval. The switch interval: a
    background thread (decoding waits, style building, fine-tunes; `service.background`) holds
    the GIL until the interval runs out whenever the event loop wants it, however low its nice
    level. hostile_bench uploads phase (`--seconds 15 --phases uploads --attacker-nice 19`, four
    alternating pairs): p99 / quiet 3.00, 2.42, 2.73, 2.49 at Python's 5 ms; 1.87, 2.22, 1.35,
    1.75 at 0.5 ms."""
    sys.setswitchinterval(settings.gil_switch_interval_s)
    set_background(placement(settings.background_nice, settings.background_cpus))


def serve_once(settings: ServiceSettings, log_level: str = "info", sockets: list | None = None) -> None:
    """This process as one server: on `sockets` if given (a worker's SO_REUSEPORT socket)."""
    tune_interpreter(settings)
    app = create_app(settings)
    config = uvicorn_config(app, settings, log_level=log_level)
    configure_logging()  # session lines with their ids, probes at debug (uvicorn.Config has just set logging up)
    DrainingServer(config, app, settings.drain_timeout_s).run(sockets=sockets)
