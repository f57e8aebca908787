"""Input skeletons: map a client's frames onto the model skeleton and the results back.

A session names its skeleton or sends a BVH header inline:
- the Bandai Namco skeleton (the models' own) passes through, reordered if its joints come in
  another order;
- a CMU skeleton (either naming variant, named "cmu" or sent as a header) is retargeted frame by
  frame on the way in and back onto the client's skeleton on the way out
  (`models.motion.retarget_stream`), causally and with no per-session state.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from models.motion import bvh as bvhio
from models.motion.retarget import source_variant
from models.motion.assets import cmu_skeleton
from models.motion.retarget_stream import FrameRetargeter
from models.motion.skeleton import Skeleton, skeleton_from_bvh

from .protocol import ProtocolError


class SkeletonAdapter(Protocol):
    joint_names: list[str]

    @property
    def num_joints(self) -> int: ...
    def to_model(self, root: np.ndarray, rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...
    def from_model(self, root: np.ndarray, rotations: np.ndarray, input_rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...


class Reorder:
    """Identity or a joint reordering between a client's joint order and the model's."""

    def __init__(self, joint_names: list[str], model_skeleton: Skeleton) -> None:
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


class Retarget:
    """A CMU-skeleton client: per-frame retargeting onto the model skeleton and back."""

    def __init__(self, source: Skeleton) -> None:
        self.joint_names = list(source.names)
        self.retargeter = FrameRetargeter(source)

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    def to_model(self, root: np.ndarray, rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        hips, rot = self.retargeter.to_model(root[None], rotations[None])
        return hips[0], rot[0]

    def from_model(self, root: np.ndarray, rotations: np.ndarray, input_rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        out_root, out_rot = self.retargeter.to_source(root[None], rotations[None], input_rotations[None])
        return out_root[0], out_rot[0]


def _for_skeleton(source: Skeleton, model_skeleton: Skeleton) -> SkeletonAdapter:
    if all(n in source.names for n in model_skeleton.names):
        return Reorder(list(source.names), model_skeleton)
    try:
        source_variant(source)
    except ValueError:
        raise ProtocolError("unsupported_skeleton",
                            "skeleton is neither the Bandai Namco skeleton nor a CMU skeleton "
                            f"(joints: {', '.join(source.names[:6])}...)", fatal=True) from None
    if source.parents[0] != -1 or source.names[0] != "Hips":
        raise ProtocolError("unsupported_skeleton", "a CMU skeleton must have Hips as its root", fatal=True)
    return Retarget(source)


def adapter_for(skeleton: str | None, bvh_header: str | None, model_skeleton: Skeleton) -> SkeletonAdapter:
    if bvh_header is not None:
        text = bvh_header.split("MOTION")[0] + "MOTION\nFrames: 0\nFrame Time: 0.0333333\n"
        try:
            parsed = bvhio.parse(text, "bvh_header")
        except bvhio.BvhError as exc:
            raise ProtocolError("bad_skeleton", str(exc), fatal=True) from None
        return _for_skeleton(skeleton_from_bvh(parsed)[0], model_skeleton)
    if skeleton == "bandai-namco":
        return Reorder(list(model_skeleton.names), model_skeleton)
    if skeleton == "cmu":
        return Retarget(cmu_skeleton())
    raise ProtocolError("unsupported_skeleton", f"skeleton {skeleton!r} is not supported", fatal=True)
