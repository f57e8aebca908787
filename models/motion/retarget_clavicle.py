"""BN's clavicles from its upper arms: the shoulder girdle the models were trained on, whatever
rig a motion comes from.

Rigs hang their collars from different places (CMU and Xia from the spine, BN beside the neck), so
a copied collar segment lies far outside BN's neutral range. In BN's neutral data the clavicle
follows the upper arm, so `retarget` lays it by that relation: per side, its direction in the
chest's frame is A u + c normalised, u the upper arm's, fitted on dataset 2's neutral training
clips (`fit`). On the way back the client's collar keeps its own rotation plus the model's change.

    python -m models.motion.retarget_clavicle   # refit and print `CLAVICLE_FROM_ARM`
"""

from __future__ import annotations

import numpy as np

from .rotations import quat_to_matrix
from .skeleton import Motion

# Per BN clavicle: (A | c) (3, 4), its direction in the chest's frame ~ A u + c (`fit`).
CLAVICLE_FROM_ARM = {
    "Shoulder_L": (
        (0.133, -0.054, -0.017, 0.159),
        (-0.094, 0.141, 0.024, -0.426),
        (-0.057, 0.06, 0.026, 0.88),
    ),
    "Shoulder_R": (
        (0.145, -0.071, 0.017, 0.051),
        (-0.055, 0.152, 0.063, -0.365),
        (0.022, -0.053, -0.008, -0.919),
    ),
}


def arm_and_clavicle(motion: Motion, clavicle: str) -> tuple[np.ndarray, np.ndarray]:
    """(u, d) (F, 3): unit upper-arm and clavicle directions in the clavicle's parent's frame."""
    sk = motion.skeleton
    local = quat_to_matrix(motion.rotations)
    world = local.copy()
    for j, p in enumerate(sk.parents):
        if p >= 0:
            world[:, j] = world[:, p] @ local[:, j]
    arm = sk.index(clavicle.replace("Shoulder", "UpperArm"))
    chest = int(sk.parents[sk.index(clavicle)])
    child = [j for j in range(sk.num_joints) if sk.parents[j] == arm][0]
    out = []
    for j, bone in ((arm, child), (sk.index(clavicle), arm)):
        v = np.einsum("fji,fj->fi", world[:, chest], world[:, j] @ sk.offsets[bone])
        out.append(v / np.linalg.norm(v, axis=-1, keepdims=True))
    return out[0], out[1]


def fit(motions: list[Motion]) -> dict[str, np.ndarray]:
    """Per BN clavicle, (A | c) (3, 4) by least squares over the motions' frames."""
    out = {}
    for name in CLAVICLE_FROM_ARM:
        pairs = [arm_and_clavicle(m, name) for m in motions]
        u = np.concatenate([p[0] for p in pairs])
        d = np.concatenate([p[1] for p in pairs])
        w, *_ = np.linalg.lstsq(np.c_[u, np.ones(len(u))], d, rcond=None)
        out[name] = w.T
    return out


def training_motions() -> list[Motion]:
    """What `CLAVICLE_FROM_ARM` is fitted on: data set 2's neutral training clips."""
    from ..data import build_index, load_motions

    return load_motions([c for c in build_index(["bandai-namco-2"]) if c.split == "train" and c.style == "normal"])


if __name__ == "__main__":
    for name, w in fit(training_motions()).items():
        print(name, np.round(w, 3).tolist())
