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


def _stylise(args: argparse.Namespace) -> int:
    import time
    from dataclasses import replace

    import numpy as np
    from tqdm import tqdm

    from models.motion import bvh
    from models.motion.render import render_contact_sheet, render_gif
    from models.motion.skeleton import from_bvh, to_bvh

    from .sdk import Client

    source = bvh.read(args.input)
    motion = from_bvh(source)
    header = args.input.read_text().split("MOTION")[0]
    client = Client(args.url, token=args.token)
    root_joint = next(j for j, joint in enumerate(source.joints) if "Xposition" in joint.channels and joint.parent >= 0) \
        if any("Xposition" in j.channels for j in source.joints[1:]) else 0  # BN animates Hips under a static root
    out_root = np.zeros((motion.num_frames, 3))
    out_rot = np.zeros_like(motion.rotations)
    period = 1.0 / (args.rate or motion.fps) if args.realtime else 0.0
    dropped = 0
    with client.session(model=args.model, style=args.style, bvh_header=header, fps=motion.fps,
                        intensity=args.intensity) as session:
        t0 = time.perf_counter()
        for t in tqdm(range(motion.num_frames), desc=f"{args.model}/{args.style}", unit="frame"):
            if period:
                time.sleep(max(0.0, t0 + t * period - time.perf_counter()))
            frame = session.stylise(motion.translations[t, root_joint], motion.rotations[t])
            out_root[t], out_rot[t] = frame.root, frame.rotations
            dropped += frame.dropped
    translations = motion.translations.copy()
    translations[:, root_joint] = out_root
    styled = replace(motion, rotations=out_rot, translations=translations)
    bvh.write(to_bvh(styled, template=source), args.output)
    print(f"{args.output}: {motion.num_frames} frames, style {args.style}, dropped {dropped}")
    if args.render:
        titles = ["input", f"{args.model} {args.style}"]
        if args.render.suffix.lower() == ".png":
            render_contact_sheet([motion, styled], args.render, frames=8, titles=titles)
        else:
            render_gif([motion, styled], args.render, titles=titles)
        print(args.render)
    return 0


def add_motion_commands(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("stylise", help="stream a BVH file through a running server and write the stylised BVH")
    p.add_argument("input", type=Path, help="BVH on the Bandai Namco or a CMU skeleton")
    p.add_argument("--model", default="lti")
    p.add_argument("--style", required=True)
    p.add_argument("--intensity", type=float, default=1.0)
    p.add_argument("-o", "--output", type=Path, required=True, help="stylised BVH (same hierarchy as the input)")
    p.add_argument("--url", default="http://127.0.0.1:8000", help="server (default http://127.0.0.1:8000)")
    p.add_argument("--token", help="API token, if the server requires one")
    p.add_argument("--realtime", action="store_true", help="send on a fixed clock instead of as fast as possible")
    p.add_argument("--rate", type=float, help="frames per second for --realtime (default: the file's frame rate)")
    p.add_argument("--render", type=Path, help="also render input vs output side by side (out.gif, or out.png)")
    p.set_defaults(func=_stylise)

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
