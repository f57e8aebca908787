"""Prometheus metrics (prometheus_client: the standard, well-kept exporter).

A private registry per app, so several apps in one process (tests) never collide.

With several worker processes on one port (`serve --workers N`) a scrape reaches one worker at
random, so each must answer for all: the supervisor sets `PROMETHEUS_MULTIPROC_DIR`, where
prometheus_client's multiprocess mode keeps every worker's counters, histograms and gauges, and
`render` sums them over the workers (live ones for the session gauge). Process metrics (RSS,
CPU, GC, Python heap) cannot be summed meaningfully and describe the worker that answered.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from dataclasses import dataclass

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Gauge,
    GCCollector,
    Histogram,
    ProcessCollector,
    generate_latest,
)
from prometheus_client.core import GaugeMetricFamily
from prometheus_client.multiprocess import MultiProcessCollector

MULTIPROC_ENV = "PROMETHEUS_MULTIPROC_DIR"

LATENCY_BUCKETS = (0.0001, 0.00025, 0.0005, 0.001, 0.002, 0.004, 0.008, 0.0167, 0.033, 0.066, 0.1, 0.25, 1.0)


@dataclass(frozen=True)
class ModelMetrics:
    """One model's labelled children, looked up once: `.labels()` hashes and locks on every
    call (~1-2 µs), and the frame path touches these on every frame."""

    frame_latency: Histogram
    frames: Counter
    direct_frames: Counter
    dropped_frames: Counter
    step_latency: Histogram
    batch_size: Histogram


class Metrics:
    def __init__(self) -> None:
        self._per_model: dict[str, ModelMetrics] = {}
        self.registry = CollectorRegistry()
        self.frame_latency = Histogram(
            "stylestream_frame_latency_seconds",
            "Server-side time from a frame's arrival to its reply being sent",
            ["model"],
            buckets=LATENCY_BUCKETS,
            registry=self.registry,
        )
        self.step_latency = Histogram(
            "stylestream_step_seconds",
            "Time of one batched model step",
            ["model"],
            buckets=LATENCY_BUCKETS,
            registry=self.registry,
        )
        self.batch_size = Histogram(
            "stylestream_batch_size",
            "Sessions per batched step",
            ["model"],
            buckets=(1, 2, 4, 8, 16, 32, 64, 128, 256, 512),
            registry=self.registry,
        )
        self.active_sessions = Gauge(
            "stylestream_active_sessions",
            "Open streaming sessions",
            ["model"],
            registry=self.registry,
            multiprocess_mode="livesum",
        )
        self.dropped_frames = Counter(
            "stylestream_dropped_frames_total", "Frames dropped by backpressure", ["model"], registry=self.registry
        )
        self.errors = Counter("stylestream_errors_total", "Client errors by code", ["code"], registry=self.registry)
        self.frames = Counter("stylestream_frames_total", "Frames stylised", ["model"], registry=self.registry)
        self.direct_frames = Counter(
            "stylestream_direct_frames_total",
            "Frames of them taken by the direct path, without an ASGI message (service.transport)",
            ["model"],
            registry=self.registry,
        )
        self.snapshots = Counter(
            "stylestream_snapshots_total", "Session snapshots written to the store", registry=self.registry
        )
        self.snapshot_failures = Counter(
            "stylestream_snapshot_failures_total",
            "Snapshot writes that failed (store unreachable); retried",
            registry=self.registry,
        )
        self.snapshot_seconds = Histogram(
            "stylestream_snapshot_write_seconds",
            "One batched write of snapshots to the store",
            buckets=LATENCY_BUCKETS,
            registry=self.registry,
        )
        self.rig_builds = Counter(
            "stylestream_rig_builds_total",
            "Rigs built in a child process, by the child that answered (idle: SCHED_IDLE; normal: "
            "the background's niceness, after the idle one starved)",
            ["child"],
            registry=self.registry,
        )
        self.resumes = Counter(
            "stylestream_sessions_resumed_total", "Sessions resumed from a snapshot", registry=self.registry
        )
        # memory, for Prometheus and the soak test: process RSS/CPU/fds and the Python heap, this process's own
        self.process_registry = CollectorRegistry()
        ProcessCollector(registry=self.process_registry)
        GCCollector(registry=self.process_registry)
        self.process_registry.register(PythonHeapCollector())

    def render(self) -> tuple[bytes, str]:
        """The `/metrics` body and content type: this process's metrics, or, under a worker
        supervisor, the sum over every worker's (see the module docstring)."""
        folder = os.environ.get(MULTIPROC_ENV)
        if folder:
            summed = CollectorRegistry()
            MultiProcessCollector(summed, path=folder)
            body = generate_latest(summed)
        else:
            body = generate_latest(self.registry)
        return body + generate_latest(self.process_registry), CONTENT_TYPE_LATEST

    def model(self, name: str) -> ModelMetrics:
        """The per-model children for `name`, created on first use."""
        children = self._per_model.get(name)
        if children is None:
            children = self._per_model[name] = ModelMetrics(
                self.frame_latency.labels(name),
                self.frames.labels(name),
                self.direct_frames.labels(name),
                self.dropped_frames.labels(name),
                self.step_latency.labels(name),
                self.batch_size.labels(name),
            )
        return children


class PythonHeapCollector:
    """`stylestream_python_allocated_blocks`: memory blocks held by Python's allocator, the heap
    size proxy the soak test watches. A collector, not a Gauge, so multiprocess mode keeps no
    file of it: it is read at scrape time in the process that answers."""

    def collect(self) -> Iterator[GaugeMetricFamily]:
        yield GaugeMetricFamily(
            "stylestream_python_allocated_blocks",
            "Memory blocks held by Python's allocator (heap size proxy)",
            value=sys.getallocatedblocks(),
        )
