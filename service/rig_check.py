"""Limits and sanity checks on a client's rig, applied before anything is built from it.

A rig is the one input whose cost the client chooses: parsing is linear in the header, but the
role matching and the retargeter's set-up grow with joints and depth (a 1,800-joint rig took
170 ms to build, a 1,000-deep chain 1.2 s to preview), and a rig with an infinite, 1e308 or
zero-length bone made the retargeter divide by zero. Each problem has its own kind, the
`RigError.code` (the REST answer's `code`, and the start of a stream error's message, whose code
is `bad_skeleton`):

- `rig_too_large`: a header over MAX_HEADER_BYTES (checked before it is parsed);
- `too_many_joints`: more than MAX_JOINTS joints;
- `rig_too_deep`: a chain more than MAX_DEPTH joints deep;
- `bad_joint_name`: a name longer than MAX_NAME_CHARS, or with a non-printable character;
- `bad_offset`: an OFFSET that is not finite or beyond MAX_OFFSET in any unit;
- `degenerate_rig`: legs of zero length, or a mapped bone the retargeter reads a direction from
  that has no length (its two joints coincide at rest), or a set-up that is not finite.
"""

from __future__ import annotations

import numpy as np

from models.motion.humanoid import HumanoidRig, RigError, bn_segments
from models.motion.skeleton import Skeleton

MAX_HEADER_BYTES = 128 * 1024  # a 512-joint hierarchy written out plainly takes ~60 kB
MAX_JOINTS = 512  # full-body rigs with fingers and twist bones have 60-250
MAX_DEPTH = 64  # the deepest chain of a humanoid with fingers is ~12-20
MAX_NAME_CHARS = 200  # as a preset's `joints` entries
MAX_OFFSET = 1e5  # 1 km in cm, 100 m in mm: beyond any humanoid in any of the accepted units
MIN_BONE = 1e-6  # of the leg length: a mapped bone shorter than this has no direction


def check_header(text: str) -> None:
    """Refuse a header too large to parse (`rig_too_large`); the part before MOTION counts."""
    head = text.split("MOTION", 1)[0]
    size = len(head.encode("utf-8", "surrogatepass"))
    if size > MAX_HEADER_BYTES:
        raise RigError("rig_too_large", f"the BVH hierarchy takes {size} bytes; at most {MAX_HEADER_BYTES} are taken")


def check_names(names: list[str] | tuple[str, ...]) -> None:
    """Refuse over-long or non-printable joint names (`bad_joint_name`)."""
    for name in names:
        if len(name) > MAX_NAME_CHARS:
            raise RigError(
                "bad_joint_name", f"a joint name of {len(name)} characters (at most {MAX_NAME_CHARS})", (name[:40],)
            )
        if not name or not name.isprintable():
            raise RigError("bad_joint_name", f"joint name {name[:40]!r} is empty or has a non-printable character")


def depths(parents: np.ndarray) -> np.ndarray:
    """Each joint's depth (the root 0); parents come first, as a parsed hierarchy has them."""
    out = np.zeros(len(parents), np.int64)
    for k, p in enumerate(parents.tolist()):
        out[k] = 0 if p < 0 else out[p] + 1
    return out


def check_skeleton(skeleton: Skeleton) -> None:
    """Joint count, depth, names and offsets of a parsed hierarchy, cheapest first."""
    count = skeleton.num_joints
    if count > MAX_JOINTS:
        raise RigError("too_many_joints", f"the rig has {count} joints; at most {MAX_JOINTS} are taken")
    deepest = int(depths(np.asarray(skeleton.parents)).max(initial=0)) + 1
    if deepest > MAX_DEPTH:
        raise RigError("rig_too_deep", f"the rig has a chain {deepest} joints deep; at most {MAX_DEPTH} are taken")
    check_names(skeleton.names)
    offsets = np.asarray(skeleton.offsets, np.float64)
    ends = np.asarray(skeleton.end_sites, np.float64)
    ends = ends[~np.isnan(ends).any(-1)]  # joints without an End Site carry NaN
    for what, values in (("OFFSET", offsets), ("End Site OFFSET", ends)):
        bad = ~np.isfinite(values).all(-1) | (np.abs(values) > MAX_OFFSET).any(-1)
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            where = f"joint {skeleton.names[k]!r}" if what == "OFFSET" else "an End Site"
            raise RigError(
                "bad_offset", f"{what} of {where} is not finite or beyond ±{MAX_OFFSET:g}: {values[k].tolist()}"
            )


def rest_positions(skeleton: Skeleton) -> np.ndarray:
    """World joint positions at rest (identity rotations: offsets summed down the tree)."""
    pos = np.zeros((skeleton.num_joints, 3))
    for k, p in enumerate(np.asarray(skeleton.parents).tolist()):
        pos[k] = skeleton.offsets[k] + (pos[p] if p >= 0 else 0.0)
    return pos


def check_rig(rig: HumanoidRig) -> None:
    """The matched rig's legs and the bones the retargeter takes directions from have length
    (`degenerate_rig`): a zero one was a division by zero in the retargeter."""
    leg = rig.leg_length
    if not np.isfinite(leg) or leg <= 0:
        raise RigError("degenerate_rig", f"the legs (thigh + shin) have length {leg:g}: the rig cannot be scaled")
    pos, roles = rest_positions(rig.skeleton), rig.roles
    pairs = list(bn_segments(roles).values()) + [("upperarm_r", "upperarm_l"), ("upperleg_r", "upperleg_l")]
    short = [
        f"{a}-{b}"
        for a, b in pairs
        if a in roles and b in roles and np.linalg.norm(pos[roles[b]] - pos[roles[a]]) <= MIN_BONE * leg
    ]
    if short:
        raise RigError("degenerate_rig", f"bones of no length at rest: {', '.join(short)}", tuple(short))
