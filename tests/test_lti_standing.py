"""Another performer standing in place, through every LTI style. The shipped translator has one
root system for all seven root features (Hsu et al.), and dataset 2's pelvis tilts with its
pace: a dataset-1 performer's standing tilt reads as pace and walks the output off. A known
failure, kept as a strict xfail: identified with the ground travel its own system
(`train.CONFIG["split_root"]`) it passes, but those weights slid more elsewhere
(docs/eval/ablation.md), so they are not shipped."""

from __future__ import annotations

import numpy as np
import pytest

from models.data import build_index, load_motions, select
from models.lti.model import LTIStyleModel

STANDING = ("bow", "call", "respond")  # dataset-1 contents performed in place
SECONDS = 5


@pytest.fixture(scope="module")
def standing():
    index = build_index(["bandai-namco-1"])
    clips = [c for c in select(index, dataset="bandai-namco-1", style="normal") if c.content in STANDING]
    return [m.slice(0, min(m.num_frames, int(SECONDS * m.fps))) for m in load_motions(clips)]


def _ground_path(motion) -> float:
    """cm the hips travel over the ground."""
    hips = motion.global_positions()[:, motion.skeleton.index("Hips"), [0, 2]]
    return float(np.linalg.norm(np.diff(hips, axis=0), axis=-1).sum())


@pytest.mark.xfail(
    strict=True,
    reason="one root system reads the pelvis tilt as pace: toward masculine the bow travels 25 cm/s, the input 4",
)
def test_a_performer_standing_in_place_is_not_walked_off(standing):
    """The translator's own root (the planter, which moves the root toward held feet, off)."""
    model = LTIStyleModel(footlock=False)
    assert len(standing) >= 3
    for style in model.styles():
        for motion in standing:
            out, _ = model.translate(motion, style)
            # the input sways 9-74 cm over these clips; split-root weights stay within this
            assert _ground_path(out) <= 1.5 * _ground_path(motion) + 10.0, style
