"""`python -m tools.bench {lti,erd,lpn,retarget} [...]`: per-frame step cost of each method's
streaming model (batch 1 and 256), and of the retargeter both ways.

The machines this runs on are shared (other jobs, a training run), and absolute timings drift by
2x or more from one minute to the next. So every step is timed interleaved with a fixed
reference workload in plain numpy (the "floor", chosen by each model: the product any
implementation of it has to do) and the report gives both medians and their ratio; the ratio is
what compares across runs and machines. The process CPU time of each step is reported too: it
leaves out the time the process waited for a core, which on a busy machine is most of the wall
time. Threads are capped like the service caps them (BLAS via threadpoolctl, torch intra-op).
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
import torch
from threadpoolctl import threadpool_limits

from models.data import build_index, load_motion, select
from models.erd.runtime import ERDModel
from models.interface import FrameBatch, StreamingModel
from models.lpn.runtime import LPNModel
from models.settings import get_settings


@contextmanager
def capped_threads(n: int) -> Iterator[None]:
    """numpy BLAS and torch intra-op threads limited to n (the service runs with 1)."""
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


def lti(args: argparse.Namespace) -> None:
    """Every stage on (as the service loads it, the unseen-content fade last), the same without
    the fade, the published core alone (the translators and the foot planter), the feet's pitch
    off and the foot lock off, timed interleaved, step by step, in one run; the floor is the paper's one dense
    [[A, B], [C, D]] @ [x; u] product of the same batch."""
    from models.lti import load
    from models.lti.model import LTIStyleModel
    from models.registry import load_model

    clip = select(build_index(["bandai-namco-2"]), style="normal", content="walk", split="val")[0]
    motion = load_motion(clip)
    folder = Path(args.weights)
    shipped_model = load_model(folder.parent, "lti")  # the weights root, as the service reads it
    assert shipped_model is not None, f"no LTI weights in {folder}"
    variants = {
        "shipped": shipped_model,  # with the unseen-content fade, as the service loads it
        "without the fade": load(folder),
        "core alone": load(folder, core_only=True),
        "feet's pitch off": LTIStyleModel(weights_dir=folder, off=("foot_pitch",)),
        "foot lock off": LTIStyleModel(weights_dir=folder, footlock=False),
    }
    shipped = variants["without the fade"]
    assert isinstance(shipped, LTIStyleModel)
    style = args.style or ("elderly" if "elderly" in shipped.styles() else shipped.styles()[0])
    tr = shipped.translators[style]
    M_T = np.ascontiguousarray(tr.M.T)
    for threads in args.threads:
        print(
            f"LTI step_batch, style {style} (state dim {tr.n}), input {clip.name}, {threads} BLAS/torch thread(s); "
            "medians of interleaved steps, process CPU time in brackets"
        )
        for batch in (1, 256):
            frames = [
                FrameBatch(
                    np.repeat(motion.translations[k : k + 1, 1], batch, 0),
                    np.repeat(motion.rotations[k : k + 1], batch, 0),
                )
                for k in range(motion.num_frames)
            ]
            weights = np.zeros((batch, len(shipped.styles())))
            weights[:, shipped.styles().index(style)] = 1.0
            zin = np.random.default_rng(0).standard_normal((batch, M_T.shape[0]))
            steps = {name: stepper(model, frames, weights, batch) for name, model in variants.items()}
            steps["floor (dense product)"] = partial(_dense_product, zin, M_T)
            repeats = args.frames if batch == 1 else max(args.frames // 8, 100)
            with capped_threads(threads):
                wall, cpu = interleaved(steps, repeats)
            base = np.median(wall["core alone"])
            for name in steps:
                w, c = np.median(wall[name]) * 1e6, np.median(cpu[name]) * 1e6
                print(
                    f"  batch {batch:4d} {name:22s}: {w:8.1f} us/step ({w / batch:6.2f} us/frame) "
                    f"[CPU {c:8.1f}], x{np.median(wall[name]) / base:5.2f} the core alone"
                )


def _dense_product(zin: np.ndarray, M_T: np.ndarray, i: int) -> None:
    np.matmul(zin, M_T)


def erd(args: argparse.Namespace) -> None:
    """The network in float32 (served) and float64 (the reference); the floor is the network's
    matrix products alone."""
    from models.erd.runtime import load

    results = []
    for threads in args.threads:
        for dtype in (np.float32, np.float64):
            model = load(get_settings().weights_dir / "erd", dtype=dtype)
            print(
                f"Style-ERD step_batch, network {np.dtype(dtype).name}, style elderly, {threads} BLAS/torch thread(s)"
            )
            for B in (1, 256):
                rng = np.random.default_rng(0)
                q = rng.normal(size=(B, 22, 4)) * 0.05 + np.array([0, 0, 0, 1.0])
                frames = FrameBatch(np.tile([[0.0, 90.0, 0.0]], (B, 1)), q / np.linalg.norm(q, axis=-1, keepdims=True))
                w = np.zeros((B, len(model.styles())))
                w[:, model.styles().index("elderly")] = 1.0
                with capped_threads(threads):
                    timing = time_steps(
                        B,
                        stepper(model, [frames], w, B),
                        _erd_products(model, B),
                        args.steps if B == 1 else max(args.steps // 4, 50),
                    )
                print(timing.line())
                results.append({"threads": threads, "dtype": np.dtype(dtype).name, **timing.as_dict()})
    if args.json:
        print(json.dumps(results, indent=1))


def _erd_products(model: ERDModel, B: int) -> Callable[[], None]:
    """The network's matrix products for B sessions and nothing else: encoder, every LSTM
    branch's input and hidden products, decoder, in the model's dtype."""
    dt, H, K = model.dtype, model.H, len(model.branches)
    rng = np.random.default_rng(1)
    x = rng.standard_normal((B, model.enc_in.shape[0])).astype(dt)
    hs = rng.standard_normal((K, B, 2 * H)).astype(dt)
    d_in = rng.standard_normal((B, model.dec[0][0].shape[0])).astype(dt)

    def floor() -> None:
        h = x @ model.enc_in
        for W, _ in model.enc:
            h = h @ W
        for W in model.lstm_w:
            np.matmul(hs, W)
        h = d_in
        for W, _ in model.dec:
            h = h @ W

    return floor


def lpn(args: argparse.Namespace) -> None:
    """Under control, against the floor of the expert products alone, one thread as served."""
    from models.lpn import load

    model = load(get_settings().weights_dir / "lpn")
    first = model.rest_motion()
    print(f"LPN-FiLM step_batch under control, style elderly, {args.threads[0]} BLAS/torch thread(s)")
    results = []
    for B in (1, 256):
        control = np.tile(np.array([[1.2, 0.0, 0.0, 0.0, 1.0]], np.float32), (B, 1))
        frames = FrameBatch(
            np.repeat(first.translations[:1, 1], B, 0), np.repeat(first.rotations[:1], B, 0), control=control
        )
        w = np.zeros((B, len(model.styles())), np.float32)
        w[:, model.styles().index("elderly")] = 1.0
        step, repeats = stepper(model, [frames], w, B), args.steps if B == 1 else max(args.steps // 4, 20)
        with capped_threads(args.threads[0]):
            timing = time_steps(B, step, _lpn_products(model, B), repeats, warmup=20)
        print(timing.line())
        results.append(timing.as_dict())
    print(json.dumps(results, indent=1))


def _lpn_products(model: LPNModel, B: int) -> Callable[[], None]:
    """The network's three expert products for B sessions and nothing else (BLAS, float32)."""
    rng = np.random.default_rng(0)
    inputs = [rng.standard_normal((B, W.shape[0])).astype(np.float32) for W, _, _ in model.layers]

    def floor() -> None:
        for h, (W, _, _) in zip(inputs, model.layers):
            h @ W

    return floor


def retarget(args: argparse.Namespace) -> None:
    """Per-frame cost of the retargeter both ways (`FrameRetargeter`), batched, per rig preset."""
    from models.motion.humanoid import preset_rig
    from models.motion.retarget_stream import FrameRetargeter

    rng = np.random.default_rng(0)
    print(f"{'preset':>8} {'joints':>6} {'batch':>6} {'to_model us/char':>17} {'to_source us/char':>18} {'both':>8}")
    for preset in args.preset or ["ue5", "mixamo", "cmu"]:
        fr = FrameRetargeter(preset_rig(preset))
        j = fr.source.num_joints
        for b in args.batch or [1, 16, 256]:
            rot = rng.normal(size=(b, j, 4)) * 0.1 + [0, 0, 0, 1]
            root = rng.normal(size=(b, 3))
            state = fr.init_state(b)  # one stream per character
            hips, bn = fr.to_model(root, rot, state)
            fr.to_source(hips, bn, rot, state)
            t0 = time.perf_counter()
            for _ in range(args.repeat):
                hips, bn = fr.to_model(root, rot, state)
            t1 = time.perf_counter()
            for _ in range(args.repeat):
                fr.to_source(hips, bn, rot, state)
            t2 = time.perf_counter()
            a, c = (t1 - t0) / args.repeat / b * 1e6, (t2 - t1) / args.repeat / b * 1e6
            print(f"{preset:>8} {j:>6} {b:>6} {a:>17.1f} {c:>18.1f} {a + c:>8.1f}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m tools.bench", description=__doc__)
    sub = ap.add_subparsers(dest="cmd", required=True)
    threads = "BLAS/torch thread caps to run with (service: 1)"
    b = sub.add_parser("lti", help=lti.__doc__)
    b.add_argument("--style")
    b.add_argument("--frames", type=int, default=2000)
    b.add_argument("--weights", default=str(get_settings().weights_dir / "lti"), help="folder of translator .npz files")
    b.add_argument("--threads", type=int, nargs="+", default=[1, 2], help=threads)
    b = sub.add_parser("erd", help=erd.__doc__)
    b.add_argument("--steps", type=int, default=400)
    b.add_argument("--threads", type=int, nargs="+", default=[1, 2], help=threads)
    b.add_argument("--json", action="store_true", help="also print the numbers as JSON")
    b = sub.add_parser("lpn", help=lpn.__doc__)
    b.add_argument("--steps", type=int, default=300, help="timed steps at batch 1 (a quarter at batch 256)")
    b.add_argument("--threads", type=int, nargs=1, default=[1], help=threads)
    b = sub.add_parser("retarget", help=retarget.__doc__)
    b.add_argument("--preset", action="append", help="presets to time (default: ue5, mixamo, cmu)")
    b.add_argument("--batch", type=int, action="append", help="characters per call (default 1, 16, 256)")
    b.add_argument("--repeat", type=int, default=20)
    args = ap.parse_args(argv)
    {"lti": lti, "erd": erd, "lpn": lpn, "retarget": retarget}[args.cmd](args)


if __name__ == "__main__":
    main()
