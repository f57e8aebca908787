"""Input skeletons: map a client's frames onto the model skeleton and the results back.

A session names its skeleton ("bandai-namco": the model skeleton as is) or sends a BVH header
inline; a header with the Bandai Namco joints in another order is reordered.
"""

from __future__ import annotations

import numpy as np

from models.motion import bvh as bvhio
from models.motion.skeleton import Skeleton

from .protocol import ProtocolError


class SkeletonAdapter:
    """Identity or a joint reordering between a client's joint order and the model's."""

    def __init__(self, joint_names: list[str], model_skeleton: Skeleton) -> None:
        missing = [n for n in model_skeleton.names if n not in joint_names]
        if missing:
            raise ProtocolError("unsupported_skeleton",
                                f"skeleton lacks the model joints {', '.join(missing[:5])}; send the Bandai Namco skeleton",
                                fatal=True)
        self.joint_names = list(joint_names)
        self.to_model_index = np.array([joint_names.index(n) for n in model_skeleton.names])
        self.identity = self.joint_names == list(model_skeleton.names)

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    def to_model(self, root: np.ndarray, rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return root, rotations if self.identity else rotations[self.to_model_index]

    def from_model(self, root: np.ndarray, rotations: np.ndarray, input_rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.identity:
            return root, rotations
        out = input_rotations.copy()  # joints the model does not have pass through unchanged
        out[self.to_model_index] = rotations
        return root, out


def adapter_for(skeleton: str | None, bvh_header: str | None, model_skeleton: Skeleton) -> SkeletonAdapter:
    if bvh_header is not None:
        text = bvh_header.split("MOTION")[0] + "MOTION\nFrames: 0\nFrame Time: 0.0333333\n"
        try:
            parsed = bvhio.parse(text, "bvh_header")
        except bvhio.BvhError as exc:
            raise ProtocolError("bad_skeleton", str(exc), fatal=True) from None
        return SkeletonAdapter(parsed.names, model_skeleton)
    if skeleton == "bandai-namco":
        return SkeletonAdapter(list(model_skeleton.names), model_skeleton)
    raise ProtocolError("unsupported_skeleton", f"skeleton {skeleton!r} is not supported", fatal=True)
