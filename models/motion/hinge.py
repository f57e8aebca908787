"""Hinge joints, fitted from real rotations, and the parent twist that keeps them hinges.

A model that decides where bones point takes twists from another pose, so an elbow or knee may
swing off its hinge. `fit_hinges` finds a parent's only child whose swing turns about one
direction, storing its axis (real bends positive), the parent's real twist interval and the least
real bend (`floor`). `twist_kernels.hinge_twist` turns the parent so the child's bone lies in the
hinge plane; the turn fades below `fade` radians of bend and from a quarter turn on.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .rotations import quat_inv, quat_log, quat_mean, quat_mul, swing_twist, twist_angle
from .skeleton import Skeleton

HINGE_FILE = "hinges.npz"
HINGE_SHARE = 0.999  # share of a joint's real swing (squared angle) about one axis that makes it a hinge
TWIST_PERCENTILES = (0.5, 99.5)  # the parent's real twist interval the re-twist stays in
FADE_DEGREES = 35.0  # below this bend the hinge plane is ill-defined: the re-twist fades to none


@dataclass(frozen=True, eq=False)  # hashed by identity: the kernel plan is cached per instance
class Hinges:
    """Per hinge joint: hinge axis, bend direction, real means and twist intervals, floor; `fade`."""

    joints: np.ndarray  # (K,) int
    axes: np.ndarray  # (K, 3)
    bend: np.ndarray  # (K, 3)
    mean: np.ndarray  # (K, 2, 4) parent, joint
    lo: np.ndarray  # (K, 2)
    hi: np.ndarray  # (K, 2)
    fade: float = float(np.radians(FADE_DEGREES))
    floor: np.ndarray | None = None  # (K,) the least real bend about the hinge axis (radians)

    def save(self, path: Path) -> Path:
        arrays = {k: getattr(self, k) for k in ("joints", "axes", "bend", "mean", "lo", "hi")}
        if self.floor is not None:
            arrays["floor"] = self.floor
        np.savez(path, fade=np.float64(self.fade), **arrays)
        return path

    @classmethod
    def load(cls, path: Path) -> Hinges:
        with np.load(path) as z:
            arrays = {k: np.asarray(z[k], np.float64) for k in ("axes", "bend", "mean", "lo", "hi")}
            floor = np.asarray(z["floor"], np.float64) if "floor" in z else None
            return cls(np.asarray(z["joints"], np.int64), fade=float(z["fade"]), floor=floor, **arrays)


def _single_bone_parent(skeleton: Skeleton, j: int) -> bool:
    """Whether j has a parent whose only child bone is j (turning the parent moves nothing else)."""
    p = int(skeleton.parents[j])
    bones = [c for c in skeleton.children(p) if np.linalg.norm(skeleton.offsets[c]) > 1e-6]
    return p >= 0 and bones == [j]


def fit_hinges(skeleton: Skeleton, rotations: np.ndarray, share: float = HINGE_SHARE) -> Hinges:
    """Hinge joints from real local rotations (N, J, 4) of every style (module docstring)."""
    from .twist import bone_axes  # twist imports this module

    q = np.asarray(rotations, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    axes = bone_axes(skeleton)
    joints, hinge, bend, mean, lo, hi, floor = [], [], [], [], [], [], []
    for j in range(skeleton.num_joints):
        if not skeleton.children(j) or not _single_bone_parent(skeleton, j):
            continue
        v = quat_log(swing_twist(q[:, j], axes[j])[0])
        vals, vecs = np.linalg.eigh(v.T @ v)
        if vals[-1] < share * vals.sum():
            continue
        h = vecs[:, -1] if np.median(v @ vecs[:, -1]) >= 0 else -vecs[:, -1]
        p = int(skeleton.parents[j])
        t = np.cross(h, axes[j])
        t -= (t @ axes[p]) * axes[p]
        m = quat_mean(q[:, [p, j]], axis=0)  # (2, 4)
        twist = twist_angle(quat_mul(quat_inv(m)[None], q[:, [p, j]]), axes[[p, j]])  # (N, 2)
        joints.append(j)
        hinge.append(h)
        bend.append(t / np.linalg.norm(t))
        mean.append(m)
        lo.append(np.percentile(twist, TWIST_PERCENTILES[0], axis=0))
        hi.append(np.percentile(twist, TWIST_PERCENTILES[1], axis=0))
        floor.append(float((v @ h).min()))
    as3 = lambda a: np.array(a).reshape(-1, 3)  # noqa: E731
    as2 = lambda a: np.array(a).reshape(-1, 2)  # noqa: E731
    means = np.array(mean).reshape(-1, 2, 4)
    return Hinges(
        np.array(joints, np.int64), as3(hinge), as3(bend), means, as2(lo), as2(hi), floor=np.array(floor, np.float64)
    )


def kernel_floor(skeleton: Skeleton, hinges: Hinges | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per joint (J) for `hinge_kernels.floor_bend`: bone axis, hinge axis, floor (-inf: not held)."""
    from .twist import bone_axes  # twist imports this module

    J = skeleton.num_joints
    hinge, floor = np.zeros((J, 3)), np.full(J, -np.inf)
    if hinges is not None and hinges.floor is not None:
        hinge[hinges.joints], floor[hinges.joints] = hinges.axes, hinges.floor
    return np.ascontiguousarray(bone_axes(skeleton), np.float64), hinge, floor


class KernelHinges(NamedTuple):
    """The hinges per joint (J), as `twist_kernels` takes them (`kernel_hinges`)."""

    child: np.ndarray  # (J,) int64 the hinge child a joint re-twists for (-1: none)
    bend: np.ndarray  # (J, 3) that child's bend direction in the joint's frame
    mean: np.ndarray  # (J, 4) real mean rotation of parents and hinge joints
    limits: np.ndarray  # (J, 2) their twist interval about it
    fade: float  # radians of bend below which the re-twist fades to none


def kernel_hinges(skeleton: Skeleton, hinges: Hinges | None) -> KernelHinges:
    """Per joint (J) for `twist_kernels`, cached (the steps call it every frame)."""
    return _kernel_hinges(tuple(map(int, skeleton.parents)), hinges)


@lru_cache(maxsize=16)
def _kernel_hinges(parents: tuple[int, ...], hinges: Hinges | None) -> KernelHinges:
    J = len(parents)
    child = np.full(J, -1, np.int64)
    bend = np.zeros((J, 3))
    mean = np.tile([0.0, 0.0, 0.0, 1.0], (J, 1))
    limits = np.tile([-np.pi, np.pi], (J, 1))
    if hinges is None:
        return KernelHinges(child, bend, mean, limits, 0.0)
    for k, j in enumerate(hinges.joints):
        p = parents[j]
        child[p], bend[p] = j, hinges.bend[k]
        mean[[p, j]] = hinges.mean[k]
        limits[[p, j]] = np.stack([hinges.lo[k], hinges.hi[k]], axis=-1)
    return KernelHinges(child, bend, mean, limits, hinges.fade)
