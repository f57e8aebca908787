"""CLI: python -m models.lti {train, hinges, translate, bench, render}.

python -m models.lti train [--styles elderly exhausted] [--align imw|dtw] [--contents walk ...]
python -m models.lti hinges   (the hinge joints and their floors -> models/weights/lti/hinges.npz)
python -m models.lti translate in.bvh --style elderly -o out.bvh [--timewarp] [--no-blend] [--no-footlock] [--model-heading]
python -m models.lti bench [--style elderly] [--frames 2000] [--threads 1 2] [--weights DIR]
python -m models.lti render [--styles elderly exhausted] [--content walk]   (PNG + GIF under out/)
"""

from __future__ import annotations

import argparse
import sys
import time
from functools import partial
from pathlib import Path

import numpy as np

# model.WEIGHTS_DIR, without importing the model
WEIGHTS_DIR_DEFAULT = Path(__file__).resolve().parents[1] / "weights" / "lti"


def cmd_train(args: argparse.Namespace) -> None:
    from .train import CONFIG, train

    cfg = dict(CONFIG)
    if args.align:
        cfg["align"] = args.align
    if args.contents:
        cfg["contents"] = args.contents
    t0 = time.time()
    from .model import WEIGHTS_DIR

    report = train(args.styles, cfg, Path(args.out) if args.out else WEIGHTS_DIR)
    print(f"trained {len(report)} styles in {time.time() - t0:.1f} s")


def cmd_hinges(args: argparse.Namespace) -> None:
    """Hinge joints and their least real bend from every dataset-2 TRAIN clip (the data LTI is
    identified on), every style: one floor for built-in and uploaded styles alike."""
    from models.motion.assets import bandai_namco_skeleton
    from models.motion.hinge import HINGE_FILE
    from models.motion.hinge_floor import fit_floor

    hinges = fit_floor(bandai_namco_skeleton())
    print(hinges.save(Path(args.out) / HINGE_FILE), "floors (deg)", np.degrees(np.asarray(hinges.floor)).round(2))


def cmd_translate(args: argparse.Namespace) -> None:
    from models.motion import bvh as bvhio
    from models.motion.skeleton import from_bvh, to_bvh

    from .model import LTIStyleModel

    model = LTIStyleModel(blend=not args.no_blend, footlock=not args.no_footlock, keep_heading=not args.model_heading)
    src = bvhio.read(args.input)
    motion = from_bvh(src)
    out, contacts = model.translate(motion, args.style, timewarp=args.timewarp)
    bvhio.write(to_bvh(out, src), args.output)
    print(
        f"{args.input} -> {args.output}: {motion.num_frames} -> {out.num_frames} frames, style {args.style}, "
        f"contacts L {contacts[:, 0].mean():.0%} R {contacts[:, 1].mean():.0%}"
    )


def cmd_bench(args: argparse.Namespace) -> None:
    """Per-frame cost of `step_batch` at batch 1 and 256, with the threads capped (1 = as the
    service runs): every stage on (as the service loads it, the unseen-content fade last), the same
    without the fade, against the published core alone (`load(...,
    core_only=True)`: the translators and the foot planter), and the foot lock off. The machines
    are shared and noisy, so the variants are timed interleaved, step by step, in one run, with
    the paper's one dense [[A, B], [C, D]] @ [x; u] product of the same batch in numpy as a
    floor; the medians' ratios are what compares across runs."""
    from models.data import build_index, load_motion, select
    from models.interface import FrameBatch
    from models.registry import load_model
    from models.stepbench import capped_threads, interleaved, stepper

    from . import load
    from .model import LTIStyleModel

    clip = select(build_index(["bandai-namco-2"]), style="normal", content="walk", split="val")[0]
    motion = load_motion(clip)
    folder = Path(args.weights)
    shipped_model = load_model(folder.parent, "lti")  # the weights root, as the service reads it
    assert shipped_model is not None, f"no LTI weights in {folder}"
    variants = {
        "shipped": shipped_model,  # with the unseen-content fade, as the service loads it
        "without the fade": load(folder),
        "core alone": load(folder, core_only=True),
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
            steps["floor (dense product)"] = partial(_floor, zin, M_T)
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


def _floor(zin: np.ndarray, M_T: np.ndarray, i: int) -> None:
    np.matmul(zin, M_T)


def cmd_render(args: argparse.Namespace) -> None:
    """Input vs translated output of a validation neutral walk: contact sheet PNG + GIF per style."""
    from models.data import build_index, load_motion, select
    from models.motion.render import render_contact_sheet, render_gif

    from .model import LTIStyleModel

    model = LTIStyleModel()
    clip = select(build_index(["bandai-namco-2"]), style="normal", content=args.content, split="val")[0]
    motion = load_motion(clip)
    out_dir = Path(args.out)
    for style in args.styles or model.styles():
        online, _ = model.translate(motion, style)
        warped, _ = model.translate(motion, style, timewarp=True)
        ms, titles = [motion, online, warped], [f"input {clip.name}", f"{style} (online)", f"{style} (time-warped)"]
        png = render_contact_sheet(ms, out_dir / f"lti_{style}_{args.content}.png", frames=8, titles=titles)
        print(f"wrote {png}")
        if not args.no_gif:
            gif = render_gif(ms, out_dir / f"lti_{style}_{args.content}.gif", titles=titles, seconds=args.seconds)
            print(f"wrote {gif}")


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(
        prog="python -m models.lti", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = p.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train")
    t.add_argument("--styles", nargs="*")
    t.add_argument("--align", choices=["imw", "dtw"])
    t.add_argument("--contents", nargs="*")
    t.add_argument("--out")
    t.set_defaults(func=cmd_train)
    h = sub.add_parser("hinges")
    h.add_argument("--out", default=str(WEIGHTS_DIR_DEFAULT))
    h.set_defaults(func=cmd_hinges)
    r = sub.add_parser("translate")
    r.add_argument("input")
    r.add_argument("--style", required=True)
    r.add_argument("-o", "--output", required=True)
    r.add_argument("--timewarp", action="store_true")
    r.add_argument("--no-blend", action="store_true")
    r.add_argument("--no-footlock", action="store_true", help="skip the IK foot lock")
    r.add_argument(
        "--model-heading", action="store_true", help="use the model's yaw change (may drift) instead of the input's"
    )
    r.set_defaults(func=cmd_translate)
    b = sub.add_parser("bench")
    b.add_argument("--style")
    b.add_argument("--frames", type=int, default=2000)
    b.add_argument("--weights", default=str(WEIGHTS_DIR_DEFAULT), help="folder of translator .npz files")
    b.add_argument(
        "--threads", type=int, nargs="+", default=[1, 2], help="BLAS/torch thread caps to run with (service: 1)"
    )
    b.set_defaults(func=cmd_bench)
    v = sub.add_parser("render")
    v.add_argument("--styles", nargs="*")
    v.add_argument("--content", default="walk")
    v.add_argument("--out", default="out")
    v.add_argument("--seconds", type=float, default=6.0)
    v.add_argument("--no-gif", action="store_true")
    v.set_defaults(func=cmd_render)
    args = p.parse_args(argv)
    args.func(args)


if __name__ == "__main__":
    main(sys.argv[1:])
