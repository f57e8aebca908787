"""Planted-joint slide, the tests' measure of feet that should hold still."""

from __future__ import annotations

import numpy as np

from models.eval.metrics import FLOOR_PERCENTILE
from models.motion.features import body_joint, left_leg_length
from models.motion.skeleton import Motion

PLANT_HEIGHT = 0.03  # leg lengths (2.5 cm on Bandai Namco) above a joint's floor level: that joint is planted


def planted_slide(motion: Motion, positions: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Horizontal speeds {"toe": (N,), "ankle": (M,)} of each joint over the frames it is near its
    own floor, both feet pooled: no flat foot needed, so a toe sliding at push-off counts."""
    sk = motion.skeleton
    pos = motion.global_positions() if positions is None else positions
    limit = PLANT_HEIGHT * left_leg_length(sk)
    out: dict[str, list[np.ndarray]] = {"toe": [], "ankle": []}
    for part in out:
        for side in "lr":
            p = pos[:, body_joint(sk, f"{part}_{side}")]
            planted = p[1:, 1] < np.percentile(p[:, 1], FLOOR_PERCENTILE) + limit
            speed = np.linalg.norm(np.diff(p[:, [0, 2]], axis=0), axis=-1) * motion.fps
            out[part].append(speed[planted])
    return {k: np.concatenate(v) for k, v in out.items()}
