"""Input skeletons: map a client's frames onto the model skeleton and the results back.

A session names a preset rig (`skeleton`, optionally with the `joints` its frames carry, in
their order) or sends a BVH header inline (`bvh_header`), plus optional `joint_map`, `units`,
`up` and `handedness`:
- the Bandai Namco skeleton (the models' own) passes through, reordered if its joints come in
  another order (extra joints pass through unchanged);
- any other humanoid (`models.motion.humanoid`: Mixamo, Unreal, Unity/VRM, SMPL, CMU, BVH
  exports, or anything whose names or `joint_map` give the body roles) is retargeted frame by
  frame on the way in and back onto the client's own rig on the way out
  (`models.motion.retarget_stream`), causally and with no per-session state.
A rig that cannot be mapped is refused with a typed error naming what is missing; nothing of it
is applied.
"""

from __future__ import annotations

import json
from functools import lru_cache
from typing import Protocol

import numpy as np

from models.motion import bvh as bvhio
from models.motion.bn_skeleton import missing_joints
from models.motion.humanoid import HumanoidRig, RigError, preset_rig, rig_from_bvh
from models.motion.retarget_stream import FrameRetargeter
from models.motion.skeleton import Skeleton, skeleton_from_bvh

from .protocol import ProtocolError


class SkeletonAdapter(Protocol):
    """A client's rig <-> the model skeleton. The `_rows` forms take many frames at once, one row
    each ((n, 3) roots, (n, J, 4) rotations: a crowd's characters of one rig); row by row they
    give exactly what the one-frame forms give."""

    joint_names: list[str]

    @property
    def num_joints(self) -> int: ...
    def to_model(self, root: np.ndarray, rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...
    def from_model(
        self, root: np.ndarray, rotations: np.ndarray, input_rotations: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]: ...
    def to_model_rows(self, root: np.ndarray, rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...
    def from_model_rows(
        self, root: np.ndarray, rotations: np.ndarray, input_rotations: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]: ...
    def report(self) -> dict: ...


class _OneFrame:
    """The one-frame forms, as rows of one."""

    def to_model_rows(self, root: np.ndarray, rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def from_model_rows(
        self, root: np.ndarray, rotations: np.ndarray, input_rotations: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def to_model(self, root: np.ndarray, rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        out_root, out_rot = self.to_model_rows(root[None], rotations[None])
        return out_root[0], out_rot[0]

    def from_model(
        self, root: np.ndarray, rotations: np.ndarray, input_rotations: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        out_root, out_rot = self.from_model_rows(root[None], rotations[None], input_rotations[None])
        return out_root[0], out_rot[0]


class Reorder(_OneFrame):
    """Identity or a joint reordering between a client's joint order and the model's."""

    def __init__(self, joint_names: list[str], model_skeleton: Skeleton) -> None:
        self.joint_names = list(joint_names)
        self.to_model_index = np.array([joint_names.index(n) for n in model_skeleton.names])
        self.identity = self.joint_names == list(model_skeleton.names)
        self.model_names = list(model_skeleton.names)

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    def to_model_rows(self, root: np.ndarray, rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return root, rotations if self.identity else rotations[:, self.to_model_index]

    def from_model_rows(
        self, root: np.ndarray, rotations: np.ndarray, input_rotations: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        if self.identity:
            return root, rotations
        out = input_rotations.copy()  # joints the model does not have pass through unchanged
        out[:, self.to_model_index] = rotations
        return root, out

    def report(self) -> dict:
        model = set(self.model_names)
        return {
            "preset": "bandai-namco",
            "retargeted": False,
            "mapping": {n: n for n in self.model_names},
            "unmapped": [n for n in self.joint_names if n not in model],
            "root_joint": "Hips",
        }


class Retarget(_OneFrame):
    """Any other humanoid: per-frame retargeting onto the model skeleton and back. The client's
    joint order may differ from the rig's internal parents-first order (`order`)."""

    def __init__(self, rig: HumanoidRig, joint_names: list[str] | None = None) -> None:
        self.rig = rig
        self.retargeter = FrameRetargeter(rig)
        internal = list(rig.skeleton.names)
        self.joint_names = list(joint_names) if joint_names is not None else internal
        self.order = None if self.joint_names == internal else np.array([self.joint_names.index(n) for n in internal])

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    def to_model_rows(self, root: np.ndarray, rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.retargeter.to_model(root, rotations if self.order is None else rotations[:, self.order])

    def from_model_rows(
        self, root: np.ndarray, rotations: np.ndarray, input_rotations: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        inp = input_rotations if self.order is None else input_rotations[:, self.order]
        out_root, out_rot = self.retargeter.to_source(root, rotations, inp)
        if self.order is None:
            return out_root, out_rot
        back = np.empty_like(out_rot)
        back[:, self.order] = out_rot
        return out_root, back

    def report(self) -> dict:
        return {**self.rig.report(), "retargeted": True}


# rig problems -> the protocol's two skeleton codes; the message starts with the precise kind
_CODES = {
    "missing_roles": "unsupported_skeleton",
    "bad_topology": "unsupported_skeleton",
    "unsupported_skeleton": "unsupported_skeleton",
}


def rig_error(err: RigError) -> ProtocolError:
    """A `RigError` as the typed, fatal protocol error: `unsupported_skeleton` for a rig that is
    not a usable humanoid, `bad_skeleton` for a malformed header, joint list or option; the
    message names every missing role or broken link."""
    return ProtocolError(_CODES.get(err.code, "bad_skeleton"), f"{err.code}: {err.message}", fatal=True)


@lru_cache(maxsize=256)
def _retarget(skeleton: str | None, bvh_header: str | None, options: str) -> Retarget:
    """The adapter for a start message's rig fields (`options` as sorted JSON). Cached: many
    sessions bring the same rig, and the adapter is stateless."""
    opts = json.loads(options)
    joints = opts.pop("joints", None)
    if bvh_header is not None:
        if joints is not None:
            raise RigError(
                "bad_skeleton",
                "give 'joints' with a preset 'skeleton', not with 'bvh_header' (its order is the header's)",
            )
        return Retarget(rig_from_bvh(bvh_header, **opts))
    if skeleton is None:  # `adapter_for` refuses that before it gets here
        raise RigError("bad_skeleton", "give a preset 'skeleton' or a 'bvh_header'")
    return Retarget(preset_rig(skeleton, joints=joints, **opts), joints)


def _as_model_world(options: dict) -> bool:
    """No option moves the rig off the model's own world (a left-handed, Z-up or metre BN rig is retargeted)."""
    return (
        not options.get("joint_map")
        and options.get("handedness", "right") == "right"
        and options.get("up") in (None, "y")
        and options.get("units") in (None, "cm")
    )


def _is_model_skeleton(names: list[str], model_skeleton: Skeleton, options: dict) -> bool:
    return not missing_joints(names, model_skeleton.names) and _as_model_world(options)


def adapter_for(
    skeleton: str | None, bvh_header: str | None, model_skeleton: Skeleton, joints: list[str] | None = None, **options
) -> SkeletonAdapter:
    """The adapter for a start message's rig; raises `ProtocolError` (fatal, typed) for a rig
    that cannot be mapped, before anything is set up."""
    if bvh_header is not None:
        text = bvh_header.split("MOTION")[0] + "MOTION\nFrames: 0\nFrame Time: 0.0333333\n"
        try:
            names = list(skeleton_from_bvh(bvhio.parse(text, "bvh_header"))[0].names)
        except bvhio.BvhError as exc:
            raise ProtocolError("bad_skeleton", str(exc), fatal=True) from None
        if _is_model_skeleton(names, model_skeleton, options):
            return Reorder(names, model_skeleton)
    elif skeleton == "bandai-namco" and _as_model_world(options):
        names = list(joints) if joints is not None else list(model_skeleton.names)
        missing = [n for n in model_skeleton.names if n not in names]
        if missing or len(set(names)) != len(names):
            raise ProtocolError(
                "bad_skeleton",
                f"joints must list every Bandai Namco joint once (missing: {', '.join(missing) or 'none'})",
                fatal=True,
            )
        return Reorder(names, model_skeleton)
    elif skeleton in (None, "custom"):
        raise ProtocolError("unsupported_skeleton", "give a preset 'skeleton' or a 'bvh_header'", fatal=True)
    try:
        return _retarget(
            skeleton if bvh_header is None else None,
            bvh_header,
            json.dumps({**options, **({"joints": joints} if joints is not None else {})}, sort_keys=True),
        )
    except RigError as err:
        raise rig_error(err) from None


def warm() -> None:
    """Load (or, on a fresh machine, compile: ~15 s) the per-frame retargeting kernels before the
    first custom-rig session rather than on its first frame: building one retargeter runs both
    directions while it measures its standing offset."""
    FrameRetargeter(preset_rig("cmu"))
