"""Retargeted feet do not sink below the floor when the client crouches, kneels, sits or lunges,
whatever its leg proportions: the root rises instead (`FrameRetargeter._drop`). Measured as the
BN lowest foot point (toe and ankle joints) against BN's toe floor, with the client's lowest foot
point on its own floor. Before, on a rig with a longer shin than BN's, a kneeling client's BN feet
sank 6.8 cm under the toe floor (2.5 cm under the ground)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from models.data import load_motion, select
from models.motion.assets import BANDAI_NAMCO_ANKLE_FLOOR, BANDAI_NAMCO_TOE_FLOOR
from models.motion.retarget import contact_height, retarget
from models.motion.retarget_stream import FrameRetargeter
from models.motion.rotations import quat_exp
from models.motion.skeleton import Skeleton, fk

from .clips import angle_deg
from .reference import retarget as reference

# (thigh forward, knee bend, ankle), degrees, about the CMU rig's lateral axis (its rest is a T-pose)
POSES = {
    "stand": (0, 0, 0),
    "crouch": (60, 120, -60),
    "sit": (90, 90, 0),
    "kneel": (0, 90, 60),  # on the tops of the feet
    "lunge": (80, 80, 0),
    "deep kneel": (20, 120, 30),
}


@pytest.fixture(scope="module")
def rigs(index) -> dict[str, FrameRetargeter]:
    """The CMU rig as it is, and with a shin longer than its thigh by more than BN's."""
    sk = load_motion(select(index, dataset="cmu", name="131_02")[0]).skeleton
    cmu = FrameRetargeter(sk)
    off = sk.offsets.copy()
    for s in "lr":
        off[cmu.humanoid.roles[f"lowerleg_{s}"]] *= 0.75  # the knee's offset: the thigh
        off[cmu.humanoid.roles[f"foot_{s}"]] *= 1.25  # the ankle's: the shin
    return {"cmu": cmu, "long shin": FrameRetargeter(replace(sk, offsets=off))}


def _pose(fr: FrameRetargeter, thigh: float, knee: float, ankle: float) -> tuple[np.ndarray, np.ndarray]:
    """(root (1, 3), rotations (1, J, 4)): both legs posed, the lowest foot point on the client's floor."""
    sk, roles = fr.source, fr.humanoid.roles
    rot = np.zeros((1, sk.num_joints, 4))
    rot[..., 3] = 1.0
    for s in "lr":
        for role, angle in (("upperleg", -thigh), ("lowerleg", knee), ("foot", ankle)):
            rot[0, roles[f"{role}_{s}"]] = quat_exp(np.array([np.radians(angle), 0.0, 0.0]))
    trans = np.broadcast_to(sk.offsets, (1, sk.num_joints, 3)).copy()
    pos = fk(rot, trans, sk.parents)[1][0]
    trans[0, fr.humanoid.translated, 1] += fr.source_floor - pos[_feet(sk, roles), 1].min()
    return trans[:, fr.humanoid.translated], rot


def _feet(sk: Skeleton, roles: dict[str, int]) -> list[int]:
    return [roles[f"{p}_{s}"] for p in ("toes", "foot") for s in "lr"]


def _bn_lowest(fr: FrameRetargeter, hips: np.ndarray, rot: np.ndarray) -> float:
    sk = fr.rig.skeleton
    trans = np.broadcast_to(sk.offsets, (1, sk.num_joints, 3)).copy()
    trans[:, sk.index("Hips")] = hips
    pos = fk(rot, trans, sk.parents)[1][0]
    return float(pos[[sk.index(f"{p}_{s}") for p in ("Toes", "Foot") for s in "LR"], 1].min())


@pytest.mark.parametrize("rig", ["cmu", "long shin"])
@pytest.mark.parametrize("pose", list(POSES))
def test_feet_stay_above_the_floor(rigs, rig, pose):
    fr = rigs[rig]
    root, rot = _pose(fr, *POSES[pose])
    hips, bn = fr.to_model(root, rot)
    assert _bn_lowest(fr, hips, bn) > fr.rig.floor - 1.0
    ref_hips, ref_bn = reference.to_model(fr, root, rot)
    np.testing.assert_allclose(hips, ref_hips, atol=1e-9)
    # and back: the client's own frame again, root included
    back_root, back_rot = fr.to_source(hips, bn, rot)
    np.testing.assert_allclose(back_root, root, atol=1e-9)
    assert angle_deg(back_rot, rot).max() < 1e-4


def test_the_root_rises_only_when_the_bn_feet_would_sink(rigs):
    """Standing, the root stays within millimetres of the plain mapping (scaled client hips plus
    the standing offset); kneeling on the long-shin rig, it rises by centimetres."""
    fr = rigs["long shin"]
    rises = {}
    for pose in ("stand", "kneel"):
        root, rot = _pose(fr, *POSES[pose])
        c = (
            reference._hips_terms(fr, reference._source_globals(fr, rot))[0] + root
        ) @ fr._axes.T  # client hips, BN axes
        rises[pose] = fr.to_model(root, rot)[0][0, 1] - (fr.scale * c[0, 1] + fr.vertical_offset)
    assert 0.0 <= rises["stand"] < 0.5
    assert rises["kneel"] > 3.0, rises


def test_retargeted_flat_feet_are_bn_flat_feet(index):
    """On every CMU and Xia clip, BN's ankle stands as high above its toe joint on a flat foot as
    in BN's own data (7.5 cm; each contact height, `retarget.contact_height`), within 2 cm. Rigs
    place the ankle and toe joints differently above the sole: copied by direction, BN's toes rose
    30 degrees off a flat CMU or Xia foot and the ankle stood 1.1-4.1 cm above the toes."""
    want = BANDAI_NAMCO_ANKLE_FLOOR - BANDAI_NAMCO_TOE_FLOOR
    clips = select(index, dataset="cmu") + select(index, dataset="xia")
    assert len(clips) >= 10
    for clip in clips:
        bn = retarget(load_motion(clip))
        sk, pos = bn.skeleton, bn.global_positions()
        for s in "LR":
            ankle, toe = (contact_height(pos[:, [sk.index(f"{j}_{s}")], 1]) for j in ("Foot", "Toes"))
            assert abs(ankle - toe - want) < 2.0, (clip.name, s, ankle - toe)
