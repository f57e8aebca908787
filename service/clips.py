"""Uploaded style clips onto the model skeleton at the model rate, or a typed 422 saying why not.

A clip comes as JSON frames on the Bandai Namco skeleton, or as a BVH on that skeleton or any
humanoid rig `models.motion.humanoid` maps (retargeted). Either way it becomes a `Motion` on the
model skeleton at 30 fps with unit quaternions, the form every method's style abilities take.
"""

from __future__ import annotations

import numpy as np

from models.motion import bvh as bvhio
from models.motion.bn_skeleton import missing_joints
from models.motion.humanoid import RigError, rig_from_bvh, rig_kind
from models.motion.resample import resample
from models.motion.retarget import retarget
from models.motion.skeleton import Motion, Skeleton, from_bvh, travel_on

from .api import ApiError, StyleUpload

MODEL_FPS = 30.0


def clip_on_skeleton(skeleton: Skeleton, root: np.ndarray, rotations: np.ndarray, fps: float) -> Motion:
    """A Motion on `skeleton` at 30 fps from a Hips track and local rotations in its joint order."""
    n = len(root)
    trans = np.broadcast_to(skeleton.offsets, (n, skeleton.num_joints, 3)).copy()
    trans[:, skeleton.index("Hips")] = root
    motion = Motion(skeleton, rotations / np.linalg.norm(rotations, axis=-1, keepdims=True), trans, float(fps))
    return motion if abs(fps - MODEL_FPS) < 1e-6 else resample(motion, MODEL_FPS)


def hips_track(motion: Motion) -> np.ndarray:
    """The (F, 3) Hips translation of a clip, as `clip_on_skeleton` takes it back."""
    return motion.translations[:, motion.skeleton.index("Hips")]


def _check_finite(*arrays: np.ndarray) -> None:
    if not all(np.all(np.isfinite(a)) for a in arrays):
        raise ApiError(422, "non_finite", "the clip contains NaN or infinite values")


def motion_from_json(upload: StyleUpload, skeleton: Skeleton) -> tuple[Motion, str]:
    """JSON frames (BN joint order) -> BN Motion at 30 fps, and the rig ('bandai-namco')."""
    try:
        root = np.asarray(upload.frames.root, dtype=np.float64)
        rot = np.asarray(upload.frames.rotations, dtype=np.float64)
    except ValueError:
        raise ApiError(
            422, "bad_frames", "frames must be rectangular arrays: root (F, 3), rotations (F, J, 4)"
        ) from None
    j = skeleton.num_joints
    if root.ndim != 2 or root.shape[1] != 3 or rot.ndim != 3 or rot.shape[1:] != (j, 4) or len(root) != len(rot):
        raise ApiError(
            422,
            "bad_skeleton" if rot.ndim == 3 and rot.shape[1] != j else "bad_frames",
            f"expected root (F, 3) and rotations (F, {j}, 4) on the Bandai Namco skeleton "
            f"(joints {', '.join(skeleton.names)}); got root {root.shape}, rotations {rot.shape}",
        )
    _check_finite(root, rot)
    if np.any(np.linalg.norm(rot, axis=-1) < 1e-6):
        raise ApiError(422, "bad_frames", "a rotation quaternion has (near) zero length")
    return clip_on_skeleton(skeleton, root, rot, upload.fps), "bandai-namco"


def motion_from_bvh(text: str, skeleton: Skeleton, parsed: bvhio.BvhFile | None = None) -> tuple[Motion, str]:
    """BVH text (BN skeleton or any humanoid rig `models.motion.humanoid` maps) -> BN Motion at
    30 fps, and the source rig (bandai-namco, or the matched preset, or 'humanoid'). `parsed`:
    the text already parsed (to check its frame rate first), so it is not parsed twice."""
    try:
        motion = from_bvh(parsed if parsed is not None else bvhio.parse(text, "upload.bvh"))
    except (bvhio.BvhError, ValueError, KeyError, IndexError) as exc:
        raise ApiError(422, "bad_bvh", f"not a readable BVH file: {exc}") from None
    _check_finite(motion.rotations, motion.translations)
    src = motion.skeleton
    if not missing_joints(src.names, skeleton.names):
        idx = [src.index(n) for n in skeleton.names]
        hips = src.index("Hips")
        motion = travel_on(motion, hips)  # travel a root joint above the hips carries, on the hips
        return clip_on_skeleton(
            skeleton, motion.translations[:, hips], motion.rotations[:, idx], motion.fps
        ), "bandai-namco"
    try:
        rig = rig_from_bvh(text, "upload.bvh")
    except RigError as err:
        raise ApiError(
            422, "unsupported_skeleton", f"the clip's skeleton is not a humanoid rig I can map: {err.message}"
        ) from None
    bn = retarget(motion, fps=MODEL_FPS, source=rig)
    idx = [bn.skeleton.index(n) for n in skeleton.names]
    kind = rig_kind(rig)
    kind = {"cmu-bvh11": "cmu"}.get(kind, kind)  # the API names presets: 'cmu' is either CMU naming
    return clip_on_skeleton(
        skeleton, bn.translations[:, bn.skeleton.index("Hips")], bn.rotations[:, idx], MODEL_FPS
    ), kind
