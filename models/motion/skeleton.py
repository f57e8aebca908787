"""Skeletons, motions and forward kinematics (numpy and batched, differentiable torch).

A `Motion` keeps local rotations (quaternions) and local translations for every joint, per frame,
since BVH allows position channels on any joint (BN animates `Hips` under a static `joint_Root`,
CMU the root); joints without them repeat their offset.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from . import bvh as bvhio
from .rotations import euler_to_quat, quat_apply, quat_canonical, quat_inv, quat_mul, quat_to_euler

if TYPE_CHECKING:
    import torch


@dataclass(frozen=True)
class Skeleton:
    names: tuple[str, ...]
    parents: np.ndarray  # (J,) int, parent index or -1; parents precede children
    offsets: np.ndarray  # (J, 3) rest translation of each joint in its parent's frame
    end_sites: np.ndarray  # (J, 3) End Site offset, NaN where a joint has none

    def __post_init__(self) -> None:
        if any(p >= i for i, p in enumerate(self.parents)):
            raise ValueError("joints must be ordered parents-first")

    @property
    def num_joints(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"no joint {name!r} in skeleton ({', '.join(self.names)})") from None

    def children(self, j: int) -> list[int]:
        return [i for i, p in enumerate(self.parents) if p == j]

    def rest_positions(self) -> np.ndarray:
        """World joint positions with every rotation identity (the pose the offsets describe)."""
        pos = np.zeros((self.num_joints, 3))
        for j, p in enumerate(self.parents):
            pos[j] = self.offsets[j] + (pos[p] if p >= 0 else 0.0)
        return pos

    def mirror_map(self) -> np.ndarray:
        """Index of each joint's left/right counterpart (itself for centre joints)."""
        pairs = [("_L", "_R"), ("Left", "Right"), ("LHip", "RHip"), ("LFingers", "RFingers"), ("LThumb", "RThumb")]
        out = np.arange(self.num_joints)
        for j, name in enumerate(self.names):
            for a, b in pairs:
                for src, dst in ((a, b), (b, a)):
                    if src in name and name.replace(src, dst) in self.names:
                        out[j] = self.names.index(name.replace(src, dst))
        return out


@dataclass
class Motion:
    skeleton: Skeleton
    rotations: np.ndarray  # (F, J, 4) local quaternions, scalar-last
    translations: np.ndarray  # (F, J, 3) local translations
    fps: float
    euler_orders: tuple[str, ...] = field(default=())  # per joint, for writing BVH back

    @property
    def num_frames(self) -> int:
        return self.rotations.shape[0]

    def global_transforms(self) -> tuple[np.ndarray, np.ndarray]:
        """World (rotations (F,J,4), positions (F,J,3))."""
        return fk(self.rotations, self.translations, self.skeleton.parents)

    def global_positions(self) -> np.ndarray:
        return self.global_transforms()[1]

    def slice(self, start: int, stop: int) -> Motion:
        return replace(self, rotations=self.rotations[start:stop], translations=self.translations[start:stop])


def travel_on(motion: Motion, joint: int) -> Motion:
    """`motion` with its ancestors' motion moved into `joint` (where readers take the travel)."""
    chain = []
    up = int(motion.skeleton.parents[joint])
    while up >= 0:
        chain.append(up)
        up = int(motion.skeleton.parents[up])
    rest = np.asarray(motion.skeleton.offsets, np.float64)[chain]
    above_rot, above_pos = motion.rotations[:, chain], motion.translations[:, chain]
    if not motion.num_frames or ((above_rot == above_rot[:1]).all() and (above_pos == rest).all()):
        return motion  # nothing above the joint moves or sits off its rest offset (or nothing is above)
    rotations, translations = motion.rotations.copy(), motion.translations.copy()
    rotations[:, chain] = motion.rotations[:1, chain]
    translations[:, chain] = rest
    g_rot, g_pos = motion.global_transforms()
    held_rot, held_pos = fk(rotations, translations, motion.skeleton.parents)
    parent = int(motion.skeleton.parents[joint])
    inv = quat_inv(held_rot[:, parent])
    rotations[:, joint] = quat_canonical(quat_mul(inv, g_rot[:, joint]))
    translations[:, joint] = quat_apply(inv, g_pos[:, joint] - held_pos[:, parent])
    return replace(motion, rotations=rotations, translations=translations)


def depths(parents: np.ndarray) -> np.ndarray:
    """(J,) each joint's depth in the tree (roots 0), for parents-first joints."""
    depth = np.zeros(len(parents), int)
    for j, p in enumerate(parents):
        depth[j] = depth[p] + 1 if p >= 0 else 0
    return depth


def fk(rotations: np.ndarray, translations: np.ndarray, parents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Forward kinematics: local (..., J, 4)/(..., J, 3) -> world rotations and positions (normalised)."""
    rotations = rotations / np.linalg.norm(rotations, axis=-1, keepdims=True)
    g_rot = np.empty(np.broadcast_shapes(rotations.shape[:-1], translations.shape[:-1]) + (4,))
    g_pos = np.empty(g_rot.shape[:-1] + (3,))
    for j, p in enumerate(parents):
        if p < 0:
            g_rot[..., j, :], g_pos[..., j, :] = rotations[..., j, :], translations[..., j, :]
        else:
            g_rot[..., j, :] = quat_mul(g_rot[..., p, :], rotations[..., j, :])
            g_pos[..., j, :] = g_pos[..., p, :] + quat_apply(g_rot[..., p, :], translations[..., j, :])
    return g_rot, g_pos


def fk_torch(
    rotations: torch.Tensor, translations: torch.Tensor, parents: np.ndarray | list[int]
) -> tuple[torch.Tensor, torch.Tensor]:
    """Batched differentiable FK (torch imported here, so numpy-only users never load it)."""
    import torch

    from .rotations_torch import quat_apply_t, quat_mul_t

    rots: list[torch.Tensor] = []
    poss: list[torch.Tensor] = []
    rotations = rotations / rotations.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    for j, p in enumerate(parents):
        if p < 0:
            rots.append(rotations[..., j, :])
            poss.append(translations[..., j, :])
        else:
            rots.append(quat_mul_t(rots[p], rotations[..., j, :]))
            poss.append(poss[p] + quat_apply_t(rots[p], translations[..., j, :]))
    return torch.stack(rots, dim=-2), torch.stack(poss, dim=-2)


# --------------------------------------------------------------------------- BVH <-> Motion


def _rotation_order(channels: list[str]) -> str:
    return "".join(c[0] for c in channels if c.endswith("rotation"))


def skeleton_from_bvh(bvh: bvhio.BvhFile) -> tuple[Skeleton, tuple[str, ...]]:
    """The hierarchy as a Skeleton, plus each joint's Euler order (for writing BVH back)."""
    joints = bvh.joints
    skeleton = Skeleton(
        names=tuple(j.name for j in joints),
        parents=np.array([j.parent for j in joints]),
        offsets=np.stack([j.offset for j in joints]),
        end_sites=np.stack([j.end_site if j.end_site is not None else np.full(3, np.nan) for j in joints]),
    )
    return skeleton, tuple(_rotation_order(j.channels) or "ZXY" for j in joints)


def from_bvh(bvh: bvhio.BvhFile) -> Motion:
    joints = bvh.joints
    num_frames, num_joints = bvh.num_frames, len(joints)
    skeleton, orders = skeleton_from_bvh(bvh)
    rotations = np.zeros((num_frames, num_joints, 4))
    rotations[..., 3] = 1.0
    translations = np.broadcast_to(skeleton.offsets, (num_frames, num_joints, 3)).copy()
    euler: dict[str, tuple[list[int], list[np.ndarray]]] = {}  # order -> joints, angle columns
    for j, (joint, sl) in enumerate(zip(joints, bvh.channel_slices)):
        values = bvh.motion[:, sl]
        for axis, name in enumerate(bvhio.POSITION_CHANNELS):
            if name in joint.channels:
                translations[:, j, axis] = values[:, joint.channels.index(name)]
        order = _rotation_order(joint.channels)
        if order:
            idx = [joint.channels.index(f"{a}rotation") for a in order]
            euler.setdefault(order, ([], []))[0].append(j)
            euler[order][1].append(values[:, idx])
    for order, (idx, angles) in euler.items():  # one vectorised conversion per Euler order
        rotations[:, idx] = euler_to_quat(np.stack(angles, axis=1), order)
    fps = float(round(bvh.fps)) if abs(bvh.fps - round(bvh.fps)) < 1e-2 else bvh.fps  # ".0083333" is 120 fps
    return Motion(skeleton, quat_canonical(rotations), translations, fps, orders)


def to_bvh(motion: Motion, template: bvhio.BvhFile | None = None) -> bvhio.BvhFile:
    """Write a motion with the template's channels (default: 6 on the root and moving joints, else 3)."""
    sk = motion.skeleton
    if template is None:
        moving = (
            np.ptp(motion.translations, axis=0).max(axis=-1) > 1e-6
            if motion.num_frames
            else np.zeros(sk.num_joints, bool)
        )
        joints = []
        for j in range(sk.num_joints):
            order = motion.euler_orders[j] if motion.euler_orders else "ZXY"
            pos = list(bvhio.POSITION_CHANNELS) if (sk.parents[j] < 0 or moving[j]) else []
            end = None if np.isnan(sk.end_sites[j]).any() else sk.end_sites[j]
            joints.append(
                bvhio.BvhJoint(
                    sk.names[j], int(sk.parents[j]), sk.offsets[j], pos + [f"{a}rotation" for a in order], end
                )
            )
    else:
        if template.names != list(sk.names):
            raise ValueError("template hierarchy does not match the motion's skeleton")
        joints = template.joints
    columns = []
    for j, joint in enumerate(joints):
        order = _rotation_order(joint.channels)
        euler = quat_to_euler(motion.rotations[:, j], order) if order else np.zeros((motion.num_frames, 0))
        for name in joint.channels:
            if name.endswith("position"):
                columns.append(motion.translations[:, j, "XYZ".index(name[0])])
            else:
                columns.append(euler[:, order.index(name[0])])
    data = np.stack(columns, axis=1) if columns else np.zeros((motion.num_frames, 0))
    return bvhio.BvhFile(joints, 1.0 / motion.fps, data)


def load(path: str | Path) -> Motion:
    return from_bvh(bvhio.read(path))
