"""`python -m tools.render_method {lti,erd} [...]`: contact sheets (PNG) and GIFs of a neutral
validation clip through one method.

    .venv/bin/python -m tools.render_method lti [--styles elderly exhausted] [--content walk]   # online and time-warped, out/
    .venv/bin/python -m tools.render_method erd [--styles elderly,exhausted] [--content walk]   # out/erd/*.png|gif
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from models.data import build_index, load_motion, load_motions, select
from models.motion.render import render_contact_sheet, render_gif
from models.settings import REPO_ROOT, get_settings
from tests.clips import stylise_stream


def lti(args: argparse.Namespace) -> None:
    """Input vs translated output (online and time-warped), one sheet and GIF per style."""
    from models.lti.model import LTIStyleModel

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


def erd(args: argparse.Namespace) -> None:
    """The input and its output in each style on one sheet (with `--reference`, real clips too)."""
    from models.erd import load

    model = load(get_settings().weights_dir / "erd")
    clips = select(build_index(["bandai-namco-2"]), split=args.split, style="normal", content=args.content)
    clip = clips[args.clip]
    motion = load_motions([clip])[0]
    styles = args.styles.split(",")
    out_dir = REPO_ROOT / "out" / "erd"
    outs, titles = [motion], [f"input ({clip.name})"]
    for style in styles:
        w = np.zeros(len(model.styles()))
        w[model.styles().index(style)] = args.intensity
        labels = {} if args.unlabelled else {"content": args.content, "input_style": "normal"}
        outs.append(stylise_stream(model, motion, w, **labels))
        titles.append(f"{style} x{args.intensity:g}" + (" (no labels)" if args.unlabelled else ""))
    if args.reference:  # real clips of the target styles, same content, for comparison
        index = build_index(["bandai-namco-2"])
        for style in styles:
            ref = select(index, split="train", style=style, content=args.content)[0]
            outs.append(load_motions([ref])[0])
            titles.append(f"real {style} ({ref.name})")
    tag = (
        f"{args.content}_{'_'.join(styles)}"
        + ("_nolabels" if args.unlabelled else "")
        + (f"_x{args.intensity:g}" if args.intensity != 1.0 else "")
        + ("_ref" if args.reference else "")
        + ("" if args.view == "10,-60" else f"_view{args.view.replace(',', '_')}")
    )
    elev, azim = (float(v) for v in args.view.split(","))
    view = (elev, azim)
    print(
        render_contact_sheet(
            outs, out_dir / f"erd_{tag}.png", frames=args.frames, titles=titles, view=view, panel_size=args.panel
        )
    )
    if args.gif:
        print(
            render_gif(
                outs[: 1 + len(styles)],
                out_dir / f"erd_{tag}.gif",
                titles=titles[: 1 + len(styles)],
                seconds=args.seconds,
            )
        )


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m tools.render_method", description=__doc__)
    sub = ap.add_subparsers(dest="cmd", required=True)
    v = sub.add_parser("lti", help=lti.__doc__)
    v.add_argument("--styles", nargs="*")
    v.add_argument("--content", default="walk")
    v.add_argument("--out", default="out")
    v.add_argument("--seconds", type=float, default=6.0)
    v.add_argument("--no-gif", action="store_true")
    r = sub.add_parser("erd", help=erd.__doc__)
    r.add_argument("--styles", default="elderly,exhausted")
    r.add_argument("--content", default="walk")
    r.add_argument("--split", default="val")
    r.add_argument("--clip", type=int, default=0)
    r.add_argument("--intensity", type=float, default=1.0)
    r.add_argument("--frames", type=int, default=8)
    r.add_argument("--seconds", type=float, default=6.0)
    r.add_argument("--unlabelled", action="store_true")
    r.add_argument("--reference", action="store_true", help="add a real training clip of each target style")
    r.add_argument("--view", default="10,-60", help="elevation,azimuth")
    r.add_argument("--panel", type=float, default=1.9)
    r.add_argument("--no-gif", dest="gif", action="store_false")
    args = ap.parse_args(argv)
    {"lti": lti, "erd": erd}[args.cmd](args)


if __name__ == "__main__":
    main()
