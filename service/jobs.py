"""Background jobs (style fine-tuning): a record per job and one worker thread off the event loop.

A job function receives a `progress(fraction, message)` callback and runs on the job thread
(numpy/scipy release the GIL in their heavy parts; one worker keeps a second fine-tune from
competing with streaming for the CPU). Records are kept in memory (`GET /v1/jobs/{id}`); the
newest `keep` finished ones are retained. A job may also be given a `record` callback that gets a
copy of its record on every change (progress at most every `RECORD_EVERY_S`): the style store
writes it next to the style, so any replica sharing the folder, or this one after a restart, can
answer for the job.
"""

from __future__ import annotations

import logging
import threading
import time
import uuid
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Literal

from pydantic import BaseModel, Field

from .background import enter_background

log = logging.getLogger(__name__)

JobStatus = Literal["queued", "running", "done", "failed"]
RECORD_EVERY_S = 0.5  # progress-only changes are recorded at most this often; status changes always


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
        self.executor = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="jobs", initializer=enter_background)
        self.jobs: dict[str, JobInfo] = {}
        self.futures: dict[str, Future] = {}
        self.keep = keep
        self._lock = threading.Lock()
        self._records: dict[str, tuple[Callable[[JobInfo], None], list[float]]] = {}  # id -> (record, [last time])

    def get(self, job_id: str) -> JobInfo | None:
        with self._lock:
            job = self.jobs.get(job_id)
            return job.model_copy() if job else None

    def _update(self, job_id: str, **fields) -> None:
        with self._lock:
            job = self.jobs[job_id]
            for k, v in fields.items():
                setattr(job, k, v)
            copy = job.model_copy()
        self._record(copy, status_changed="status" in fields)

    def _record(self, job: JobInfo, status_changed: bool = True) -> None:
        record, last = self._records.get(job.id, (None, [0.0]))
        now = time.monotonic()
        if record is None or (not status_changed and now - last[0] < RECORD_EVERY_S):
            return
        last[0] = now
        try:
            record(job)
        except Exception:  # noqa: BLE001 - a record that cannot be written must not fail the job
            log.exception("could not record job %s", job.id)

    def submit(
        self,
        kind: str,
        fn: Callable[[Callable[[float, str], None]], dict | None],
        target: str | None = None,
        on_failure: Callable[[str], None] | None = None,
        record: Callable[[JobInfo], None] | None = None,
    ) -> JobInfo:
        job = JobInfo(id=uuid.uuid4().hex, kind=kind, target=target, created=time.time(), message="queued")
        with self._lock:
            self.jobs[job.id] = job
            if record is not None:
                self._records[job.id] = (record, [0.0])
            self._trim()
        self._record(job.model_copy())

        def progress(fraction: float, message: str) -> None:
            self._update(job.id, progress=float(min(max(fraction, 0.0), 1.0)), message=message)

        def run() -> None:
            self._update(job.id, status="running", started=time.time(), message="running")
            try:
                result = fn(progress)
            except Exception as exc:  # noqa: BLE001 - a failed job is a record, not a crash
                log.exception("job %s (%s) failed", job.id, kind)
                self._update(job.id, status="failed", finished=time.time(), message=f"{type(exc).__name__}: {exc}")
                self._records.pop(job.id, None)
                if on_failure is not None:
                    try:
                        on_failure(str(exc))
                    except Exception:  # noqa: BLE001
                        log.exception("job %s failure handler failed", job.id)
                return
            self._update(job.id, status="done", progress=1.0, finished=time.time(), message="done", result=result)
            self._records.pop(job.id, None)

        self.futures[job.id] = self.executor.submit(run)
        return job.model_copy()

    def _trim(self) -> None:
        finished = [j for j in self.jobs.values() if j.status in ("done", "failed")]
        for job in sorted(finished, key=lambda j: j.created)[: max(0, len(finished) - self.keep)]:
            self.jobs.pop(job.id, None)
            self.futures.pop(job.id, None)

    def shutdown(self) -> None:
        self.executor.shutdown(wait=False, cancel_futures=True)
