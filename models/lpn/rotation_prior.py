"""Fit LPN-FiLM's rotation prior (`BALLS_FILE`): one ball per built-in style from all its
TRAIN clips, every content, since LPN-FiLM is scored on every input.

    .venv/bin/python -m models.lpn.rotation_prior [inner_q outer_q margin_deg]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from ..motion.rotation_ball import StyleBalls

BALLS_FILE = "rotation_prior.npz"
INNER_Q, OUTER_Q, MARGIN_DEG = 97.0, 99.0, 1.0


def train_rotations(styles: list[str]) -> dict[str, np.ndarray]:
    """Per style: local rotations (F, 22, 4) of every TRAIN frame of the style (all contents)."""
    from ..data import build_index, load_motions, select
    from .dataset import D1, D2

    index = build_index([D1, D2])
    out = {}
    for style in styles:
        dataset, name = (D1, style[3:]) if style.startswith("d1-") else (D2, style)
        clips = select(index, dataset=dataset, split="train", style=name)
        if clips:
            out[style] = np.concatenate([m.rotations for m in load_motions(clips)]).astype(np.float64)
    return out


def fit(styles: list[str], inner_q: float = INNER_Q, outer_q: float = OUTER_Q, margin_deg: float = MARGIN_DEG):
    return StyleBalls.fit_styles(
        train_rotations(styles), inner_q, outer_q, margin_deg, "Bandai Namco TRAIN split, all contents"
    )


def main(argv: list[str]) -> None:
    import json

    from ..settings import get_settings
    from .weights import CONFIG_FILE

    folder = get_settings().weights_dir / "lpn"
    q = [float(a) for a in argv[:3]] if argv else [INNER_Q, OUTER_Q, MARGIN_DEG]
    styles = json.loads((folder / CONFIG_FILE).read_text())["styles"]
    balls = fit(styles, *q)
    print(balls.save(Path(folder) / BALLS_FILE), balls.styles, balls.fit)


if __name__ == "__main__":
    main(sys.argv[1:])
