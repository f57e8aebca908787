"""Per-frame step cost of a streaming model, shared by the `bench` commands of the three methods.

The machines this runs on are shared (other jobs, a training run), and absolute timings drift by
2x or more from one minute to the next. So every step is timed interleaved with a fixed
reference workload in plain numpy (the "floor", chosen by each model: the product any
implementation of it has to do) and the report gives both medians and their ratio; the ratio is
what compares across runs and machines. The process CPU time of each step is reported too: it
leaves out the time the process waited for a core, which on a busy machine is most of the wall
time. Threads are capped like the service caps them (BLAS via threadpoolctl, torch intra-op).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .interface import StreamingModel


@contextmanager
def capped_threads(n: int) -> Iterator[None]:
    """numpy BLAS and torch intra-op threads limited to n (the service runs with 1)."""
    import torch
    from threadpoolctl import threadpool_limits

    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        with threadpool_limits(n, user_api="blas"):
            yield
    finally:
        torch.set_num_threads(before)


@dataclass
class StepTiming:
    batch: int
    step: np.ndarray  # wall seconds per step_batch call
    cpu: np.ndarray  # process CPU seconds per step_batch call (all threads)
    floor: np.ndarray  # wall seconds per floor call, interleaved with the steps

    @property
    def median(self) -> float:
        return float(np.median(self.step))

    @property
    def ratio(self) -> float:
        return self.median / float(np.median(self.floor))

    def as_dict(self) -> dict[str, float]:
        return {
            "batch": self.batch,
            "median_us_per_step": self.median * 1e6,
            "us_per_frame": self.median * 1e6 / self.batch,
            "p99_us_per_step": float(np.percentile(self.step, 99)) * 1e6,
            "frames_per_s": self.batch / self.median,
            "cpu_median_us_per_step": float(np.median(self.cpu)) * 1e6,
            "frames_per_cpu_s": self.batch / float(np.median(self.cpu)),
            "floor_median_us": float(np.median(self.floor)) * 1e6,
            "step_over_floor": self.ratio,
        }

    def line(self) -> str:
        d = self.as_dict()
        return (
            f"  batch {self.batch:4d}: median {d['median_us_per_step']:8.1f} us/step ({d['us_per_frame']:7.2f} us/frame), "
            f"p99 {d['p99_us_per_step']:8.1f} us/step, {d['frames_per_s']:8.0f} frames/s | "
            f"CPU {d['cpu_median_us_per_step']:8.1f} us/step ({d['frames_per_cpu_s']:7.0f} frames/CPU-s) | "
            f"floor {d['floor_median_us']:7.1f} us, step/floor {d['step_over_floor']:5.2f}"
        )


def stepper(model: StreamingModel, frames: Sequence, weights: np.ndarray, batch: int) -> Callable[[int], None]:
    """step(i) advances `batch` fresh sessions of `model` by frames[i % len(frames)]."""
    state = model.init_state(batch)

    def step(i: int) -> None:
        nonlocal state
        state = model.step_batch(state, frames[i % len(frames)], weights)[1]

    return step


def time_steps(
    batch: int, step: Callable[[int], None], floor: Callable[[], None], repeats: int, warmup: int = 10
) -> StepTiming:
    """Time `step(i)` (advances the model one frame; i counts calls) and `floor()` alternately."""
    for i in range(warmup):
        step(i)
        floor()
    steps, cpus, floors = np.empty(repeats), np.empty(repeats), np.empty(repeats)
    clock, cpu_clock = time.perf_counter, time.process_time
    for i in range(repeats):
        c0, t0 = cpu_clock(), clock()
        step(warmup + i)
        t1, c1 = clock(), cpu_clock()
        floor()
        t2 = clock()
        steps[i], cpus[i], floors[i] = t1 - t0, c1 - c0, t2 - t1
    return StepTiming(batch, steps, cpus, floors)


def interleaved(steps: dict, repeats: int, warmup: int = 10) -> tuple[dict, dict]:
    """Wall and process CPU seconds of each step(i) of `steps` (name -> step), called in turn,
    `repeats` times after `warmup` untimed rounds: the variants share the machine's drifting load."""
    for i in range(warmup):
        for step in steps.values():
            step(i)
    wall = {name: np.empty(repeats) for name in steps}
    cpu = {name: np.empty(repeats) for name in steps}
    for i in range(repeats):
        for name, step in steps.items():
            c0, t0 = time.process_time(), time.perf_counter()
            step(warmup + i)
            wall[name][i], cpu[name][i] = time.perf_counter() - t0, time.process_time() - c0
    return wall, cpu
