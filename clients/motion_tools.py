"""`stylestream render` and `stylestream retarget`: motion files in, pictures or BVH out."""

from __future__ import annotations

import argparse
from pathlib import Path


def _load_any(path: str, to_model_skeleton: bool):
    from models.motion.retarget import retarget, source_variant
    from models.motion.skeleton import load

    motion = load(path)
    if to_model_skeleton:
        try:
            source_variant(motion.skeleton)
        except ValueError:
            return motion  # already a Bandai Namco skeleton
        return retarget(motion)
    return motion


def _render(args: argparse.Namespace) -> int:
    from models.motion.render import render_contact_sheet, render_gif

    motions = [_load_any(p, args.retarget) for p in args.inputs]
    titles = args.title or [Path(p).stem for p in args.inputs]
    if args.output.suffix.lower() == ".png":
        render_contact_sheet(motions, args.output, frames=args.frames, titles=titles)
    else:
        render_gif(motions, args.output, fps=args.fps, seconds=args.seconds, titles=titles)
    print(args.output)
    return 0


def _retarget(args: argparse.Namespace) -> int:
    from models.motion import bvh
    from models.motion.retarget import retarget
    from models.motion.skeleton import load, to_bvh

    out = retarget(load(args.input), fps=args.fps)
    bvh.write(to_bvh(out), args.output)
    print(f"{args.output}: {out.num_frames} frames at {out.fps:g} fps on the Bandai Namco skeleton")
    return 0


def add_motion_commands(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("render", help="render BVH files side by side to a GIF (or a PNG contact sheet)")
    p.add_argument("inputs", nargs="+", help="BVH files (Bandai Namco or CMU skeleton)")
    p.add_argument("-o", "--output", type=Path, required=True, help="out.gif, or out.png for a contact sheet")
    p.add_argument("--title", action="append", help="panel title per input (default: file names)")
    p.add_argument("--retarget", action="store_true", help="show CMU-skeleton inputs retargeted onto the model skeleton")
    p.add_argument("--fps", type=float, default=15.0, help="GIF frame rate (default 15)")
    p.add_argument("--seconds", type=float, default=6.0, help="GIF length cap (default 6)")
    p.add_argument("--frames", type=int, default=8, help="poses per motion in a contact sheet (default 8)")
    p.set_defaults(func=_render)

    p = sub.add_parser("retarget", help="CMU-skeleton BVH (CMU/Xia files) -> Bandai Namco-skeleton BVH")
    p.add_argument("input", help="a CMU-skeleton BVH file")
    p.add_argument("-o", "--output", type=Path, required=True)
    p.add_argument("--fps", type=float, default=30.0, help="output frame rate (default 30, the models' rate)")
    p.set_defaults(func=_retarget)
