"""LPN-FiLM command line.

.venv/bin/python -m models.lpn train [--minutes 60] [--field=value ...]   # train.TrainConfig, then export
.venv/bin/python -m models.lpn fit [STYLE ...] [--stages carriage,...]    # refit the stages after the network
.venv/bin/python -m models.lpn demo [--seconds 60] [--styles normal,elderly]  # scripted control, out/lpn/
.venv/bin/python -m models.lpn bench [--steps 300] [--threads 1]       # step time, batch 1 and 256, vs the expert products alone
.venv/bin/python -m models.lpn heldout [--steps 300 --seed 0]          # new styles from a clip, 3 held-out styles
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..settings import REPO_ROOT

if TYPE_CHECKING:
    from .runtime import LPNModel


def train(args: argparse.Namespace) -> None:
    from .train import main as train_main

    train_main([f"--minutes={args.minutes}", *args.options])


def _model() -> LPNModel:
    from ..settings import get_settings
    from . import load

    return load(get_settings().weights_dir / "lpn")


def demo(args: argparse.Namespace) -> None:
    from .demo import render_demo

    out = Path(args.out)
    out = out if out.is_absolute() else REPO_ROOT / out
    png = render_demo(out, tag=args.tag, seconds=args.seconds, styles=tuple(args.styles.split(",")), gif=args.gif)
    print(png)
    print(png.with_suffix(".json").read_text())


def bench(args: argparse.Namespace) -> None:
    """Step time at batch 1 and 256 against the floor (the expert products alone), each step timed
    beside a floor call (`models/stepbench.py`); one thread, as the service runs."""
    from ..interface import FrameBatch
    from ..stepbench import capped_threads, stepper, time_steps

    model = _model()
    first = model.rest_motion()
    print(f"LPN-FiLM step_batch under control, style elderly, {args.threads} BLAS/torch thread(s)")
    results = []
    for B in (1, 256):
        control = np.tile(np.array([[1.2, 0.0, 0.0, 0.0, 1.0]], np.float32), (B, 1))
        frames = FrameBatch(
            np.repeat(first.translations[:1, 1], B, 0), np.repeat(first.rotations[:1], B, 0), control=control
        )
        w = np.zeros((B, len(model.styles())), np.float32)
        w[:, model.styles().index("elderly")] = 1.0
        step, repeats = stepper(model, [frames], w, B), args.steps if B == 1 else max(args.steps // 4, 20)
        with capped_threads(args.threads):
            timing = time_steps(B, step, _products(model, B), repeats, warmup=20)
        print(timing.line())
        results.append(timing.as_dict())
    print(json.dumps(results, indent=1))


def _products(model: LPNModel, B: int) -> Callable[[], None]:
    """The network's three expert products for B sessions and nothing else (BLAS, float32)."""
    rng = np.random.default_rng(0)
    inputs = [rng.standard_normal((B, W.shape[0])).astype(np.float32) for W, _, _ in model.layers]

    def floor() -> None:
        for h, (W, _, _) in zip(inputs, model.layers):
            h @ W

    return floor


def fit(args: argparse.Namespace) -> None:
    """Refit the declared stages (`runtime.STAGES`, default all) in their order, each from real
    clips on the committed model with the stages before it; named styles only: the file keeps its
    other styles. The stages after a refitted one were fitted on top of it: refit them too."""
    import time

    import torch

    from ..settings import get_settings
    from .runtime import STAGES, load

    torch.set_num_threads(1)
    folder = get_settings().weights_dir / "lpn"
    names = args.stages.split(",") if args.stages else [s.name for s in STAGES]
    unknown = set(names) - {s.name for s in STAGES}
    if unknown:
        raise SystemExit(f"unknown stages {sorted(unknown)}; declared: {[s.name for s in STAGES]}")
    for spec in (s for s in STAGES if s.name in names):
        t0, path = time.time(), folder / spec.file
        model = load(folder)
        stage = spec.fit(model, args.styles or None)
        if args.styles and path.exists() and hasattr(stage, "with_styles_of"):
            stage = spec.load(path, model.skeleton).with_styles_of(stage)  # type: ignore[attr-defined]
        print(f"{spec.name}: wrote {stage.save(path)} in {time.time() - t0:.0f} s")


def heldout(args: argparse.Namespace) -> None:
    import torch

    from .finetune import FineTuneConfig
    from .heldout import evaluate

    torch.set_num_threads(1)  # as the service's fine-tune job runs
    given = {k: v for k, v in (("steps", args.steps), ("seed", args.seed)) if v is not None}
    cfg = FineTuneConfig(**given, dropout=args.dropout)
    print(json.dumps(evaluate(_model(), REPO_ROOT / "out" / "lpn", fine_tune_config=cfg), indent=1))


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m models.lpn")
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("demo", help="scripted control sequence in each style: renders + skating/freezing numbers")
    s.add_argument("--seconds", type=float, default=60.0)
    s.add_argument("--styles", default="normal,active,elderly,exhausted,feminine,masculine,youthful")
    s.add_argument("--tag", default="demo")
    s.add_argument("--out", default="out/lpn")
    s.add_argument("--no-gif", dest="gif", action="store_false")
    s.set_defaults(fn=demo)
    s = sub.add_parser("bench", help="per-frame step time at batch 1 and 256, against the expert products alone")
    s.add_argument("--steps", type=int, default=300, help="timed steps at batch 1 (a quarter at batch 256)")
    s.add_argument("--threads", type=int, default=1, help="BLAS/torch threads (the service runs with 1)")
    s.set_defaults(fn=bench)
    s = sub.add_parser(
        "heldout", help="held-out styles from a clip, instant and fine-tuned: distances to the real style, renders"
    )
    s.add_argument("--steps", type=int, help="fine-tune steps (default: FineTuneConfig's)")
    s.add_argument("--seed", type=int, help="fine-tune seed (default: FineTuneConfig's)")
    s.add_argument(
        "--no-dropout", dest="dropout", action="store_false", help="fine-tune with the network's dropout off"
    )
    s.set_defaults(fn=heldout)
    s = sub.add_parser("fit", help="refit the stages after the network from real clips (runtime.STAGES, in order)")
    s.add_argument("styles", nargs="*", help="only these styles (default: every style each stage fits)")
    s.add_argument("--stages", default="", help="comma-separated stage names (default: all)")
    s.set_defaults(fn=fit)
    s = sub.add_parser("train", help="train LPN-FiLM (options of train.TrainConfig as --field=value)")
    s.add_argument("--minutes", type=float, default=60.0)
    s.set_defaults(fn=train)
    args, rest = p.parse_known_args(argv)
    if rest and args.cmd != "train":
        p.error(f"unrecognized arguments: {' '.join(rest)}")
    args.options = rest
    args.fn(args)


if __name__ == "__main__":
    main()
