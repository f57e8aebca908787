"""`models.motion.twist.transfer_twist` in plain numpy, batched over leading axes: the reference
the compiled kernel (`models/motion/twist_kernels.py`) is tested against."""

from __future__ import annotations

import numpy as np

from models.motion.rotations import cross, quat_apply, quat_inv, quat_mul
from models.motion.skeleton import Skeleton
from models.motion.twist import _plan


def rotation_between(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(..., 4) smallest rotation carrying unit vectors u onto v; about any axis perpendicular to
    u when they are opposite."""
    d = np.sum(u * v, axis=-1, keepdims=True)
    axis = cross(u, v)
    q = np.concatenate([axis, 1.0 + d], axis=-1)
    opposite = q[..., 3] < 1e-9
    if np.any(opposite):
        ortho = cross(u[opposite], np.array([1.0, 0.0, 0.0]))
        weak = np.linalg.norm(ortho, axis=-1) < 1e-6
        ortho[weak] = cross(u[opposite][weak], np.array([0.0, 1.0, 0.0]))
        q[opposite] = np.concatenate([ortho, np.zeros(ortho.shape[:-1] + (1,))], axis=-1)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def transfer_twist_numpy(
    skeleton: Skeleton, source: np.ndarray, pose: np.ndarray, keep: tuple[str, ...] = ()
) -> np.ndarray:
    """(..., J, 4) local rotations with `pose`'s joint positions and `source`'s twists and leaf
    rotations (see the module docstring). `source` and `pose` are (..., J, 4) local rotations on
    `skeleton`; joints named in `keep` take `pose`'s local rotation as it is (their bone still
    lands where `pose` puts it)."""
    source = source / np.linalg.norm(source, axis=-1, keepdims=True)
    pose = pose / np.linalg.norm(pose, axis=-1, keepdims=True)
    out = np.empty_like(pose)
    g_pose = np.empty_like(pose)  # world rotations of `pose`
    g_new = np.empty_like(pose)  # world rotations of the result
    for j, p, kind, axis in _plan(skeleton):
        if kind == "root":
            g_pose[..., j, :] = g_new[..., j, :] = out[..., j, :] = pose[..., j, :]
            continue
        g_pose[..., j, :] = quat_mul(g_pose[..., p, :], pose[..., j, :])
        if kind == "frame":
            g_new[..., j, :] = g_pose[..., j, :]
        else:
            g = quat_mul(g_new[..., p, :], (pose if skeleton.names[j] in keep else source)[..., j, :])
            if kind == "bone":
                g = quat_mul(rotation_between(quat_apply(g, axis), quat_apply(g_pose[..., j, :], axis)), g)
            g_new[..., j, :] = g
        out[..., j, :] = quat_mul(quat_inv(g_new[..., p, :]), g_new[..., j, :])
    return out
