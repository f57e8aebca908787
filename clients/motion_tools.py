"""`stylestream render` and `stylestream retarget`: motion files in, pictures or BVH out."""

from __future__ import annotations

import argparse
from pathlib import Path


def _load_any(path: str, to_model_skeleton: bool):
    """A BVH file as a motion: with `to_model_skeleton`, any humanoid rig retargeted onto the model
    skeleton (the model's own skeleton as it is); otherwise as it is, turned Y up in cm for
    drawing. A rig that is not a humanoid raises `RigError` (one line from the CLI)."""
    from models.motion import bvh
    from models.motion.bn_skeleton import missing_joints
    from models.motion.humanoid import RigError, in_model_world, rig_from_bvh
    from models.motion.retarget import retarget
    from models.motion.skeleton import from_bvh

    text = Path(path).read_text()
    motion = from_bvh(bvh.parse(text, str(path)))
    if not missing_joints(motion.skeleton.names):
        return motion  # already the model skeleton
    try:
        rig = rig_from_bvh(text, str(path))
    except RigError:
        if to_model_skeleton:
            raise
        return motion  # not a humanoid: drawn as it is
    return retarget(motion, fps=motion.fps, source=rig) if to_model_skeleton else in_model_world(motion, rig)


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
    from models.motion.humanoid import rig_from_bvh
    from models.motion.retarget import retarget
    from models.motion.skeleton import from_bvh, to_bvh

    text = Path(args.input).read_text()
    out = retarget(from_bvh(bvh.parse(text, str(args.input))), fps=args.fps, source=rig_from_bvh(text, str(args.input)))
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
    from models.motion.skeleton import from_bvh, to_bvh, travel_on

    from .sdk import Client

    source = bvh.read(args.input)
    motion = from_bvh(source)
    header = args.input.read_text().split("MOTION")[0]
    client = Client(args.url, token=args.token)
    out_root = np.zeros((motion.num_frames, 3))
    out_rot = np.zeros_like(motion.rotations)
    period = 1.0 / (args.rate or motion.fps) if args.realtime else 0.0
    dropped = 0
    with client.session(
        model=args.model,
        style=args.style,
        bvh_header=header,
        fps=motion.fps,
        intensity=args.intensity,
        pipeline=args.pipeline,
    ) as session:
        # the joint whose translation frames carry: the server says (`rig.root_joint`; BN animates
        # Hips under a static root, other rigs their hips or their root)
        root_joint = session.joints.index(session.info.get("rig", {}).get("root_joint", session.joints[0]))
        # a file that moves a joint above it (a travelling root joint over the hips) sends that
        # travel on the root joint: frames carry one translation
        motion = travel_on(motion, root_joint)
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
        shown = [motion, styled]
        if session.info.get("rig", {}).get("retargeted"):  # drawn Y up, in cm
            from models.motion.humanoid import in_model_world, rig_from_bvh

            rig = rig_from_bvh(header)
            shown = [in_model_world(m, rig) for m in shown]
        if args.render.suffix.lower() == ".png":
            render_contact_sheet(shown, args.render, frames=8, titles=titles)
        else:
            render_gif(shown, args.render, titles=titles)
        print(args.render)
    return 0


def add_motion_commands(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("stylise", help="stream a BVH file through a running server and write the stylised BVH")
    p.add_argument(
        "input", type=Path, help="BVH on any humanoid rig (Bandai Namco, CMU, Mixamo, Unreal, Unity/VRM, SMPL, ...)"
    )
    p.add_argument("--model", default="lti")
    p.add_argument("--style", required=True)
    p.add_argument("--intensity", type=float, default=1.0)
    p.add_argument(
        "--pipeline",
        choices=["full", "core"],
        default="full",
        help="full: the shipped pipeline (default); core: the method's published core alone",
    )
    p.add_argument("-o", "--output", type=Path, required=True, help="stylised BVH (same hierarchy as the input)")
    p.add_argument("--url", default="http://127.0.0.1:8000", help="server (default http://127.0.0.1:8000)")
    p.add_argument("--token", help="API token, if the server requires one")
    p.add_argument("--realtime", action="store_true", help="send on a fixed clock instead of as fast as possible")
    p.add_argument("--rate", type=float, help="frames per second for --realtime (default: the file's frame rate)")
    p.add_argument("--render", type=Path, help="also render input vs output side by side (out.gif, or out.png)")
    p.set_defaults(func=_stylise)

    p = sub.add_parser("render", help="render BVH files side by side to a GIF (or a PNG contact sheet)")
    p.add_argument("inputs", nargs="+", help="BVH files (any rig; humanoids are drawn Y up in cm)")
    p.add_argument("-o", "--output", type=Path, required=True, help="out.gif, or out.png for a contact sheet")
    p.add_argument("--title", action="append", help="panel title per input (default: file names)")
    p.add_argument("--retarget", action="store_true", help="show humanoid inputs retargeted onto the model skeleton")
    p.add_argument("--fps", type=float, default=15.0, help="GIF frame rate (default 15)")
    p.add_argument("--seconds", type=float, default=6.0, help="GIF length cap (default 6)")
    p.add_argument("--frames", type=int, default=8, help="poses per motion in a contact sheet (default 8)")
    p.set_defaults(func=_render)

    p = sub.add_parser("retarget", help="any humanoid BVH (CMU, Mixamo, Unreal, ...) -> Bandai Namco-skeleton BVH")
    p.add_argument("input", help="a humanoid BVH file")
    p.add_argument("-o", "--output", type=Path, required=True)
    p.add_argument("--fps", type=float, default=30.0, help="output frame rate (default 30, the models' rate)")
    p.set_defaults(func=_retarget)
