"""LPN-FiLM's rotation prior (`BALLS_FILE`, `python -m models.lpn fit --stages rotation_balls`):
one ball per built-in style from all its TRAIN clips, every content, since LPN-FiLM is scored on
every input."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..motion.rotation_ball import StyleBalls

if TYPE_CHECKING:
    from .runtime import LPNModel

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


def fit(
    model: LPNModel,
    styles: list[str] | None = None,
    inner_q: float = INNER_Q,
    outer_q: float = OUTER_Q,
    margin: float = MARGIN_DEG,
) -> StyleBalls:
    """The balls of `styles` (default: every style of `model`; those without TRAIN clips get none)."""
    rotations = train_rotations(styles or model.styles())
    return StyleBalls.fit_styles(rotations, inner_q, outer_q, margin, "Bandai Namco TRAIN split, all contents")
