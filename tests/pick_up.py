"""A walk that stops to crouch and pick something up, then walks on: content none of the models
was trained on (their data walks, runs, waves and raises its arms), made from a real capture on
any rig `humanoid` matches, for the unseen-content fade's tests.

The base clip walks to a frame where both feet are down, holds there while the legs blend into a
crouch (thighs forward, knees bent, ankles flexed, the spine bent forward) and back out, then walks
on from that frame. The hips sink so that the lowest foot point stays where it stood.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from models.motion.humanoid import humanoid_rig
from models.motion.rotations import quat_exp, quat_mul
from models.motion.skeleton import Motion

# degrees about the rig's lateral axis, from its rest pose: the retargeting tests' crouch, deeper at the hip
THIGH, KNEE, ANKLE, SPINE = 80.0, 120.0, -50.0, 35.0


@dataclass(frozen=True)
class PickUp:
    motion: Motion
    crouch: tuple[float, float]  # seconds: the legs leave the walk's pose, and are back in it
    down: tuple[float, float]  # seconds: fully crouched


def pick_up(base: Motion, walk_s: float = 2.0, ramp_s: float = 0.6, hold_s: float = 1.2) -> PickUp:
    """`base` (a walk whose rest pose has the legs straight down and the lateral axis along X, as
    CMU and Xia captures have) with a pick-up inserted after about `walk_s` seconds."""
    roles = humanoid_rig(base.skeleton).roles
    fps = base.fps
    pos = base.global_positions()
    feet = [roles[f"{p}_{s}"] for p in ("foot", "toes") for s in "lr"]
    lo, hi = int(walk_s * fps), int((walk_s + 1.0) * fps)
    k = lo + int(np.argmin(pos[lo:hi, feet, 1].max(axis=1)))  # both feet down
    ramp, hold = int(ramp_s * fps), int(hold_s * fps)
    n = 2 * ramp + hold
    x = np.clip(np.concatenate([np.arange(ramp) / ramp, np.ones(hold), 1.0 - np.arange(ramp) / ramp]), 0, 1)
    s = x * x * (3.0 - 2.0 * x)  # 0 -> 1 -> 0, smooth
    rot = np.repeat(base.rotations[k : k + 1].astype(np.float64), n, axis=0)
    trans = np.repeat(base.translations[k : k + 1].astype(np.float64), n, axis=0)
    axis = np.array([1.0, 0.0, 0.0])
    for side in "lr":
        for role, angle in (("upperleg", -THIGH), ("lowerleg", KNEE), ("foot", ANKLE)):
            j = roles[f"{role}_{side}"]
            rot[:, j] = _slerp(rot[:, j], quat_exp(np.radians(angle) * axis)[None], s)
    spine = roles["spine1"]
    rot[:, spine] = quat_mul(rot[:, spine], quat_exp(np.radians(SPINE) * s[:, None] * axis))
    held = replace(base, rotations=rot, translations=trans)
    floor = pos[k, feet, 1].min()
    hips = roles["hips"]
    trans[:, hips, 1] += floor - held.global_positions()[:, feet, 1].min(axis=1)
    rotations = np.concatenate([base.rotations[:k], rot, base.rotations[k:]]).astype(np.float64)
    translations = np.concatenate([base.translations[:k], trans, base.translations[k:]]).astype(np.float64)
    motion = replace(base, rotations=rotations, translations=translations)
    return PickUp(motion, (k / fps, (k + n) / fps), ((k + ramp) / fps, (k + ramp + hold) / fps))


def _slerp(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    from models.motion.rotations import quat_inv, quat_log

    rel = quat_mul(quat_inv(a), b)
    rel = np.where(rel[..., 3:] < 0, -rel, rel)
    return quat_mul(a, quat_exp(t[:, None] * quat_log(rel)))
