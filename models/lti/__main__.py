"""CLI: python -m models.lti {train, hinges, translate}.

python -m models.lti train [--styles elderly exhausted] [--contents walk ...]
python -m models.lti hinges   (the hinge joints and their floors -> models/weights/lti/hinges.npz)
python -m models.lti translate in.bvh --style elderly -o out.bvh [--timewarp] [--no-blend] [--no-footlock] [--model-heading]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

# model.WEIGHTS_DIR, without importing the model
WEIGHTS_DIR_DEFAULT = Path(__file__).resolve().parents[1] / "weights" / "lti"


def cmd_train(args: argparse.Namespace) -> None:
    from .train import CONFIG, train

    cfg = dict(CONFIG)
    if args.contents:
        cfg["contents"] = args.contents
    t0 = time.time()
    from .model import WEIGHTS_DIR

    report = train(args.styles, cfg, Path(args.out) if args.out else WEIGHTS_DIR)
    print(f"trained {len(report)} styles in {time.time() - t0:.1f} s")


def cmd_hinges(args: argparse.Namespace) -> None:
    """Hinge joints and floors from every dataset-2 TRAIN clip, one floor for all styles."""
    from models.motion.assets import bandai_namco_skeleton
    from models.motion.hinge import HINGE_FILE
    from models.motion.hinge_floor import fit_floor

    hinges = fit_floor(bandai_namco_skeleton())
    print(hinges.save(Path(args.out) / HINGE_FILE), "floors (deg)", np.degrees(np.asarray(hinges.floor)).round(2))


def cmd_translate(args: argparse.Namespace) -> None:
    from models.motion import bvh as bvhio
    from models.motion.skeleton import from_bvh, to_bvh, travel_on

    from .model import LTIStyleModel

    model = LTIStyleModel(blend=not args.no_blend, footlock=not args.no_footlock, keep_heading=not args.model_heading)
    src = bvhio.read(args.input)
    motion = from_bvh(src)
    motion = travel_on(motion, motion.skeleton.index("Hips"))  # the translator reads the travel on the hips
    out, contacts = model.translate(motion, args.style, timewarp=args.timewarp)
    bvhio.write(to_bvh(out, src), args.output)
    print(
        f"{args.input} -> {args.output}: {motion.num_frames} -> {out.num_frames} frames, style {args.style}, "
        f"contacts L {contacts[:, 0].mean():.0%} R {contacts[:, 1].mean():.0%}"
    )


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(
        prog="python -m models.lti", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = p.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train")
    t.add_argument("--styles", nargs="*")
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
    args = p.parse_args(argv)
    args.func(args)


if __name__ == "__main__":
    main(sys.argv[1:])
