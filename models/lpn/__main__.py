"""LPN-FiLM command line.

.venv/bin/python -m models.lpn train [--minutes 60] [--field=value ...]   # train.TrainConfig, then export
.venv/bin/python -m models.lpn fit [STYLE ...] [--stages carriage,...]    # refit the stages after the network
"""

from __future__ import annotations

import argparse


def train(args: argparse.Namespace) -> None:
    from .train import main as train_main

    train_main([f"--minutes={args.minutes}", *args.options])


def fit(args: argparse.Namespace) -> None:
    """Refit the declared stages (default all) in order; stages after a refitted one need refitting too."""
    import time

    import torch

    from ..settings import get_settings
    from ..stages import refit
    from .runtime import STAGES, load

    torch.set_num_threads(1)
    folder = get_settings().weights_dir / "lpn"
    names = args.stages.split(",") if args.stages else [s.name for s in STAGES]
    unknown = set(names) - {s.name for s in STAGES}
    if unknown:
        raise SystemExit(f"unknown stages {sorted(unknown)}; declared: {[s.name for s in STAGES]}")
    for spec in (s for s in STAGES if s.name in names):
        t0, path = time.time(), refit(spec, load(folder), folder, args.styles or None)
        print(f"{spec.name}: wrote {path} in {time.time() - t0:.0f} s")


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m models.lpn")
    sub = p.add_subparsers(dest="cmd", required=True)
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
