"""Style-ERD command line.

.venv/bin/python -m models.erd fit [STYLE ...] [--stages leaf_prior,...]            # refit the decoding's hinges and the stages
"""

from __future__ import annotations

import argparse

from ..settings import get_settings
from ..stages import refit

HINGES, SOURCES = "hinges", "upload_sources"  # `fit`'s steps besides the stages: the decoding's, uploads'


def fit(args: argparse.Namespace) -> None:
    """Refit the decoding's hinges, the stages and upload sources (or those in `--stages`), in order."""
    import time

    import torch

    from .runtime import load
    from .stages import STAGES

    torch.set_num_threads(1)
    folder = get_settings().weights_dir / "erd"
    fits = [HINGES, *(s.name for s in STAGES), SOURCES]
    names = args.stages.split(",") if args.stages else fits
    if set(names) - set(fits):
        raise SystemExit(f"unknown stages {sorted(set(names) - set(fits))}; declared: {fits}")
    for name in (n for n in fits if n in names):
        t0 = time.time()
        if name == HINGES:
            from ..motion.assets import bandai_namco_skeleton
            from ..motion.hinge import HINGE_FILE
            from .dataset import load_split, split_hinges

            path = split_hinges(load_split("train"), bandai_namco_skeleton()).save(folder / HINGE_FILE)
        elif name == SOURCES:
            from .upload_stages import SOURCES_FILE, fit_sources

            path = fit_sources(load(folder)).save(folder / SOURCES_FILE)
        else:
            path = refit(next(s for s in STAGES if s.name == name), load(folder), folder, args.styles or None)
        print(f"{name}: wrote {path} in {time.time() - t0:.0f} s", flush=True)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m models.erd")
    sub = ap.add_subparsers(dest="cmd", required=True)
    f = sub.add_parser("fit", help="refit the decoding's hinges, the stages after the network and the upload sources")
    f.add_argument("styles", nargs="*", help="only these styles (default: every style each stage fits)")
    f.add_argument("--stages", default="", help="comma-separated names (default: all, in order)")
    args = ap.parse_args(argv)
    {"fit": fit}[args.cmd](args)


if __name__ == "__main__":
    main()
