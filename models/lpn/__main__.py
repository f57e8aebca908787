"""LPN-FiLM command line.

    .venv/bin/python -m models.lpn phases-plot [--out out/lpn_phases.png] [--styles 2:normal,2:elderly,1:chimpira]
    .venv/bin/python -m models.lpn phases-stats [--style normal]       # step vs fitted frequency, L/R offsets
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from ..settings import REPO_ROOT


def _styles(spec: str) -> tuple[tuple[str, str], ...]:
    out = []
    for item in spec.split(","):
        ds, style = item.split(":")
        out.append((f"bandai-namco-{ds}", style))
    return tuple(out)


def phases_plot(args) -> None:
    from .plots import DEFAULT_STYLES, phases_figure
    styles = _styles(args.styles) if args.styles else DEFAULT_STYLES
    out = Path(args.out)
    print(phases_figure(out if out.is_absolute() else REPO_ROOT / out, styles, content=args.content,
                        bones=tuple(args.bones.split(",")), seconds=args.seconds))


def phases_stats(args) -> None:
    """Per clip: step frequency from contact touchdowns vs the median fitted foot frequency, and the
    circular mean of the left-right phase difference of feet and hands (pi = anti-phase)."""
    from models.data import build_index, load_motion, select
    from .phases import circular_mean, local_phases, step_frequency
    index = build_index(["bandai-namco-1", "bandai-namco-2"])
    rows = []
    for clip in select(index, style=args.style, content=args.content, split=args.split):
        lp = local_phases(load_motion(clip))
        steps = [step_frequency(lp.contacts[:, s], lp.fps) for s in (0, 1)]
        rows.append({"clip": clip.name, "step_hz": np.round(steps, 3).tolist(),
                     "fitted_hz": np.round(np.median(lp.frequency, axis=0), 3).tolist(),
                     "feet_lr_offset": round(abs(circular_mean(lp.phase[:, 2] - lp.phase[:, 3])), 3),
                     "hands_lr_offset": round(abs(circular_mean(lp.phase[:, 0] - lp.phase[:, 1])), 3)})
        print(json.dumps(rows[-1]))


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m models.lpn")
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("phases-plot", help="Figure-4 analogue: sources, fits, phases per style")
    s.add_argument("--out", default="out/lpn_phases.png")
    s.add_argument("--styles", default="", help="comma list of dataset:style, e.g. 2:normal,1:chimpira")
    s.add_argument("--content", default="walk")
    s.add_argument("--bones", default="Foot_L,Hand_L")
    s.add_argument("--seconds", type=float, default=4.0)
    s.set_defaults(fn=phases_plot)
    s = sub.add_parser("phases-stats", help="step vs fitted frequency and L/R phase offsets per clip")
    s.add_argument("--style", default="normal")
    s.add_argument("--content", default="walk")
    s.add_argument("--split", default="train")
    s.set_defaults(fn=phases_stats)
    args = p.parse_args(argv)
    args.fn(args)


if __name__ == "__main__":
    main()
