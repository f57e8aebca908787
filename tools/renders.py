"""`python -m tools.renders [--style S ...] [--out DIR]`: oriented contact sheets of inputs
from other sources (a CMU capture, a Xia walk, a dataset-1 neutral clip) through every method,
as a user would look at them: the head, hands and feet are solids that show where they face
(`models/motion/render.py`), so a twisted wrist or a turned head shows where no metric looks.

One sheet per input and style: the input on top, then each method as shipped, then each core.
Writes palette PNGs (tens of KB) into docs/eval/renders/ by default."""

from __future__ import annotations

import argparse
from pathlib import Path

from models.data import build_index, load_motion, select
from models.eval.run import stylise_toward
from models.motion.render import render_contact_sheet
from models.motion.retarget import retarget
from models.registry import load_models
from models.settings import REPO_ROOT, get_settings

# (dataset, clip): other sources than the models' training data, none of them a test input
INPUTS = (("cmu", "131_02"), ("xia", "neutral_walk_01_000"), ("bandai-namco-1", "dataset-1_walk_normal_001"))
SECONDS = 4.0


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m tools.renders", description=__doc__)
    ap.add_argument("--style", nargs="+", default=["elderly", "feminine"])
    ap.add_argument("--out", type=Path, default=REPO_ROOT / "docs" / "eval" / "renders")
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    weights = get_settings().weights_dir
    variants = {**load_models(weights), **{f"{k} core": v for k, v in load_models(weights, core_only=True).items()}}
    index = build_index()
    for dataset, name in INPUTS:
        clip = select(index, dataset=dataset, name=name)[0]
        motion = load_motion(clip)
        motion = motion if clip.skeleton == "bandai-namco" else retarget(motion)
        motion = motion.slice(0, int(SECONDS * motion.fps))
        outs = {k: stylise_toward(m, [motion], a.style) for k, m in variants.items()}
        for style in a.style:
            rows = [motion] + [outs[k][style][0] for k in variants]
            titles = [f"input: {dataset} {name}"] + [f"{k} -> {style}" for k in variants]
            path = a.out / f"{dataset}_{style}.png"
            render_contact_sheet(rows, path, frames=6, titles=titles, dpi=60, panel_size=1.7)
            _quantise(path)
            print(path)


def _quantise(path: Path) -> None:
    from PIL import Image

    Image.open(path).convert("RGB").quantize(64).save(path, optimize=True)


if __name__ == "__main__":
    main()
