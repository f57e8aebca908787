"""Background jobs (style fine-tuning): a record per job and one worker thread off the event loop.

A job function receives a `progress(fraction, message)` callback and runs on the job thread
(numpy/scipy release the GIL in their heavy parts; one worker keeps a second fine-tune from
competing with streaming for the CPU). Records are kept in memory (`GET /v1/jobs/{id}`); the
newest `keep` finished ones are retained.
"""

from __future__ import annotations

import logging
import threading
import time
import uuid
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Callable, Literal

from pydantic import BaseModel, Field

log = logging.getLogger(__name__)

JobStatus = Literal["queued", "running", "done", "failed"]


class JobInfo(BaseModel):
    id: str
    kind: str
    status: JobStatus = "queued"
    progress: float = Field(default=0.0, ge=0.0, le=1.0)
    message: str = ""
    target: str | None = Field(default=None, description="What the job produces (a style id).")
    created: float
    started: float | None = None
    finished: float | None = None
    result: dict[str, Any] | None = None


class JobManager:
    def __init__(self, workers: int = 1, keep: int = 200) -> None:
        self.executor = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="jobs")
        self.jobs: dict[str, JobInfo] = {}
        self.futures: dict[str, Future] = {}
        self.keep = keep
        self._lock = threading.Lock()

    def get(self, job_id: str) -> JobInfo | None:
        with self._lock:
            job = self.jobs.get(job_id)
            return job.model_copy() if job else None

    def _update(self, job_id: str, **fields) -> None:
        with self._lock:
            job = self.jobs[job_id]
            for k, v in fields.items():
                setattr(job, k, v)

    def submit(self, kind: str, fn: Callable[[Callable[[float, str], None]], dict | None], target: str | None = None,
               on_failure: Callable[[str], None] | None = None) -> JobInfo:
        job = JobInfo(id=uuid.uuid4().hex, kind=kind, target=target, created=time.time(), message="queued")
        with self._lock:
            self.jobs[job.id] = job
            self._trim()

        def progress(fraction: float, message: str) -> None:
            self._update(job.id, progress=float(min(max(fraction, 0.0), 1.0)), message=message)

        def run() -> None:
            self._update(job.id, status="running", started=time.time(), message="running")
            try:
                result = fn(progress)
            except Exception as exc:  # noqa: BLE001 - a failed job is a record, not a crash
                log.exception("job %s (%s) failed", job.id, kind)
                self._update(job.id, status="failed", finished=time.time(), message=f"{type(exc).__name__}: {exc}")
                if on_failure is not None:
                    try:
                        on_failure(str(exc))
                    except Exception:  # noqa: BLE001
                        log.exception("job %s failure handler failed", job.id)
                return
            self._update(job.id, status="done", progress=1.0, finished=time.time(), message="done", result=result)

        self.futures[job.id] = self.executor.submit(run)
        return job.model_copy()

    def _trim(self) -> None:
        finished = [j for j in self.jobs.values() if j.status in ("done", "failed")]
        for job in sorted(finished, key=lambda j: j.created)[: max(0, len(finished) - self.keep)]:
            self.jobs.pop(job.id, None)
            self.futures.pop(job.id, None)

    def shutdown(self) -> None:
        self.executor.shutdown(wait=False, cancel_futures=True)
