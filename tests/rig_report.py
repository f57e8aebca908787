"""Made rigs through a live server, measured and drawn (the figures and pictures of docs/performance.md
and docs/renders):

    .venv/bin/python -m tests.rig_report errors [--frames 90]    # round-trip error per rig per model
    .venv/bin/python -m tests.rig_report render [--out docs/renders]

`errors`: every made rig (tests/rigs.py: the nine preset-named rigs and the Xsens-style capture
export) streams a Bandai Namco validation walk through LTI, Style-ERD and LPN-FiLM (elderly); the
error is the distance between the rig's mapped joints and the same walk's output on the model rig,
both relative to the hips, median over joints and frames, in % of the leg (80 cm); and how far
apart the two outputs' root paths end on the ground.

`render`: the Xsens-style rig (names no preset has, four spine joints, Z up, metres, A-pose rest)
through each model in two styles, drawn on its own hierarchy with the oriented renderer.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from models.motion.skeleton import fk

from .rigs import EXTRA_SPECS, SPECS, bn_positions, make_rig, mapped_error, stream, stream_made_rig

MODELS = ("lti", "erd", "lpn")
LEG_CM = 80.0


def _walk(frames: int):
    from models.data import build_index, load_motion, select

    clip = select(
        build_index(["bandai-namco-2"]), dataset="bandai-namco-2", style="normal", content="walk", split="val"
    )[0]
    return load_motion(clip).slice(0, frames)


def _server():
    from models.registry import load_models
    from models.settings import get_settings

    from .live_server import live_server

    models = load_models(get_settings().weights_dir)
    return live_server({m: models[m] for m in MODELS})


def errors(frames: int) -> None:
    walk = _walk(frames)
    specs = {**SPECS, "xsens": EXTRA_SPECS["xsens"]}
    with _server() as (base, _):
        bn = {}
        for model in MODELS:
            _, root, rot = stream(base, {"skeleton": "bandai-namco"}, walk.translations[:, 1], walk.rotations, model)
            trans = walk.translations.copy()
            trans[:, 1] = root
            bn[model] = fk(rot, trans, walk.skeleton.parents)[1]
        print(
            f"round trip: made rig -> model -> made rig vs the model rig's output, {frames} frames of a BN walk, elderly;"
        )
        print("median (p95) over mapped joints and frames, % of leg length; then how far apart (cm) the two root paths")
        print("end on the ground\n")
        print("| rig | naming | rest | units | up | " + " | ".join(MODELS) + " |")
        print("|---|---|---|---|---|" + "---|" * len(MODELS))
        for name, spec in specs.items():
            cells = []
            for model in MODELS:
                _, styled = stream_made_rig(base, make_rig(walk, spec), spec, model)
                err = mapped_error(styled, spec, bn[model], walk.skeleton) / LEG_CM * 100
                hips = bn_positions(styled, spec)[-1, styled.skeleton.index(spec.rename["Hips"])]
                apart = np.linalg.norm((hips - bn[model][-1, walk.skeleton.index("Hips")])[[0, 2]])
                cells.append(f"{np.median(err):.2f} ({np.percentile(err, 95):.1f}); {apart:.0f}")
            print(
                f"| {name} | {spec.rename['Hips']}, {spec.rename['UpperArm_L']} | {spec.rest} | "
                f"{'m' if spec.metres else 'cm'} | {spec.up} | " + " | ".join(cells) + " |"
            )


def render(out: Path, frames: int, styles: tuple[str, str] = ("elderly", "active")) -> None:
    from models.motion.render import render_contact_sheet

    walk = _walk(frames)
    spec = EXTRA_SPECS["xsens"]
    made = make_rig(walk, spec)
    with _server() as (base, _):
        for model in MODELS:
            rows, titles = [made], ["input: Xsens-style rig"]
            for style in styles:
                started, styled = stream_made_rig(base, made, spec, model, style)
                assert started["rig"]["up"] == "z" and started["rig"]["units"] == "m", started["rig"]
                rows.append(styled)
                titles.append(f"{model} -> {style}")
            path = render_contact_sheet(
                rows, out / f"rig_xsens_{model}.png", frames=5, titles=titles, panel_size=2.3, dpi=80
            )
            print(path, f"{path.stat().st_size / 1024:.0f} KB")


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="python -m tests.rig_report")
    sub = p.add_subparsers(dest="command", required=True)
    e = sub.add_parser("errors")
    e.add_argument("--frames", type=int, default=90)
    r = sub.add_parser("render")
    r.add_argument("--out", type=Path, default=Path("docs/renders"))
    r.add_argument("--frames", type=int, default=90)
    args = p.parse_args(argv)
    if args.command == "errors":
        errors(args.frames)
    else:
        render(args.out, args.frames)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
