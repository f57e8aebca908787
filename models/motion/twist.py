"""Keep a pose's positions, take its twists from another pose.

A model trained on joint positions never learns how a bone or leaf (head, hands, toes) turns about
itself. `transfer_twist` re-expresses `pose` with the fewest changes from `source` (the input frame)
that keep its positions: one-child joints swing onto `pose`'s bone, multi-child joints take `pose`'s
rotation, leaves keep `source`'s; with `hinges` a hinge's parent lays the child in the hinge plane.
`transfer_twist_t` is the torch twin training differentiates (reference: `tests/reference/twist.py`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np

from .bn_skeleton import body_joints
from .hinge import Hinges, kernel_hinges
from .rotations import quat_exp, quat_inv, quat_log, quat_mul
from .skeleton import Skeleton
from .twist_kernels import BONE, FRAME, LEAF, ROOT, TwistPlan, transfer_twist_batch

if TYPE_CHECKING:
    import torch

_MIN_BONE = 1e-6


def _plan(skeleton: Skeleton) -> tuple[tuple[int, int, str, np.ndarray | None], ...]:
    """Cached per skeleton (Skeleton holds arrays, so it is keyed by its contents)."""
    return _plan_cached(skeleton.names, tuple(map(int, skeleton.parents)), skeleton.offsets.tobytes())


@lru_cache(maxsize=16)
def _plan_cached(names: tuple[str, ...], parents: tuple[int, ...], offsets: bytes) -> tuple:
    """Per joint (j, parent, kind, bone axis): kind "root", "frame", "bone" or "leaf"."""
    off = np.frombuffer(offsets).reshape(len(names), 3)
    plan = []
    body_root = body_joints(names)[0]
    for j, p in enumerate(parents):
        bones = [c for c, q in enumerate(parents) if q == j and np.linalg.norm(off[c]) > _MIN_BONE]
        if p < 0:
            plan.append((j, int(p), "root", None))
        elif j == body_root or len(bones) > 1:
            plan.append((j, int(p), "frame", None))
        elif bones:
            axis = off[bones[0]]
            plan.append((j, int(p), "bone", axis / np.linalg.norm(axis)))
        else:
            plan.append((j, int(p), "leaf", None))
    return tuple(plan)


def transfer_twist(
    skeleton: Skeleton,
    source: np.ndarray,
    pose: np.ndarray,
    keep: tuple[str, ...] = (),
    hinges: Hinges | None = None,
) -> np.ndarray:
    """(..., J, 4) rotations with `pose`'s positions, `source`'s twists and leaves (`keep`: `pose`'s)."""
    J = skeleton.num_joints
    shape = np.broadcast_shapes(np.shape(source), np.shape(pose))
    src = np.ascontiguousarray(np.broadcast_to(source, shape), dtype=np.float64).reshape(-1, J, 4)
    pos = np.ascontiguousarray(np.broadcast_to(pose, shape), dtype=np.float64).reshape(-1, J, 4)
    out = np.empty_like(pos)
    transfer_twist_batch(_kernel_plan(skeleton, keep), kernel_hinges(skeleton, hinges), src, pos, out)
    return out.reshape(shape)


def _kernel_plan(skeleton: Skeleton, keep: tuple[str, ...]) -> TwistPlan:
    """The plan as the kernel takes it, cached per skeleton and `keep` (called every frame)."""
    return _kernel_plan_cached(skeleton.names, tuple(map(int, skeleton.parents)), skeleton.offsets.tobytes(), keep)


@lru_cache(maxsize=16)
def _kernel_plan_cached(
    names: tuple[str, ...], parents: tuple[int, ...], offsets: bytes, keep: tuple[str, ...]
) -> TwistPlan:
    plan = _plan_cached(names, parents, offsets)
    code = {"root": ROOT, "frame": FRAME, "bone": BONE, "leaf": LEAF}
    kinds = np.array([code[k] for _, _, k, _ in plan], dtype=np.int64)
    parent_index = np.array(parents, dtype=np.int64)
    axes = np.array([a if a is not None else (1.0, 0.0, 0.0) for _, _, _, a in plan], dtype=np.float64)
    return TwistPlan(kinds, parent_index, axes, np.array([n in keep for n in names]))


def transfer_twist_t(
    skeleton: Skeleton, source: torch.Tensor, pose: torch.Tensor, hinges: Hinges | None = None
) -> torch.Tensor:
    """`transfer_twist` in torch, differentiable in `pose` (torch imported only here)."""
    import torch

    from .rotations_torch import quat_apply_t, quat_mul_t

    hinge_child, bend, mean, limits, fade = kernel_hinges(skeleton, hinges)

    source = source / source.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    pose = pose / pose.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    g_pose: list[torch.Tensor] = []
    g_new: list[torch.Tensor] = []
    out: list[torch.Tensor] = []
    plan = _plan(skeleton)
    as_t = lambda v: torch.as_tensor(v, dtype=pose.dtype, device=pose.device)  # noqa: E731
    turned: dict[int, torch.Tensor] = {}  # hinge joint -> how far its parent turned about its bone
    for j, p, kind, axis in plan:
        if kind == "root":
            g_pose.append(pose[..., j, :])
            g_new.append(pose[..., j, :])
            out.append(pose[..., j, :])
            continue
        g_pose.append(quat_mul_t(g_pose[p], pose[..., j, :]))
        if kind == "frame":
            g = g_pose[j]
        else:
            local = source[..., j, :]
            if j in turned:  # turns back as far as its twist interval allows
                a = as_t(axis).expand(local.shape[:-1] + (3,))
                rel = quat_mul_t(as_t(mean[j] * (-1, -1, -1, 1)).expand(local.shape), local)
                local = quat_mul_t(local, _turn_t(a, _clamped_twist_t(rel, a, -turned[j], limits[j])))
            g = quat_mul_t(g_new[p], local)
            if kind == "bone":
                a = as_t(axis).expand(g.shape[:-1] + (3,))
                g = quat_mul_t(_rotation_between_t(quat_apply_t(g, a), quat_apply_t(g_pose[j], a)), g)
                k = int(hinge_child[j])
                if k >= 0:
                    g_child = quat_mul_t(g_pose[j], pose[..., k, :])
                    inv = torch.cat([-g_new[p][..., :3], g_new[p][..., 3:]], dim=-1)
                    rel = quat_mul_t(as_t(mean[j] * (-1, -1, -1, 1)).expand(g.shape), quat_mul_t(inv, g))
                    tau = _hinge_twist_t(g, g_child, a, as_t(plan[k][3]), as_t(bend[j]), fade)
                    turned[k] = _clamped_twist_t(rel, a, tau, limits[j])
                    g = quat_mul_t(g, _turn_t(a, turned[k]))
        g_new.append(g)
        inv = torch.cat([-g_new[p][..., :3], g_new[p][..., 3:]], dim=-1)
        out.append(quat_mul_t(inv, g))
    return torch.stack(out, dim=-2)


def _hinge_twist_t(
    g: torch.Tensor,
    g_child: torch.Tensor,
    axis: torch.Tensor,
    child_axis: torch.Tensor,
    bend: torch.Tensor,
    fade: float,
) -> torch.Tensor:
    """`twist_kernels.hinge_twist` in torch, before the twist interval (`_clamped_twist_t`)."""
    import torch

    from .rotations_torch import quat_apply_t

    inv = torch.cat([-g[..., :3], g[..., 3:]], dim=-1)
    d = quat_apply_t(inv, quat_apply_t(g_child, child_axis.expand(axis.shape)))
    across = d - (d * axis).sum(-1, keepdim=True) * axis
    b = bend.expand(axis.shape)
    tau = torch.atan2((torch.linalg.cross(b, across) * axis).sum(-1), (across * b).sum(-1))
    weight = (2.0 - 2.0 * tau.abs() / math.pi).clamp(0.0, 1.0)
    if fade > 0.0:
        weight = weight * (across.pow(2).sum(-1).clamp_min(1e-12).sqrt() / math.sin(fade)).clamp(max=1.0)
    return tau * weight


def _clamped_twist_t(
    rel: torch.Tensor, axis: torch.Tensor, turn: torch.Tensor, limits: Sequence[float]
) -> torch.Tensor:
    """`twist_kernels.clamped_twist` in torch."""
    import torch

    twist = 2.0 * torch.atan2((rel[..., :3] * axis).sum(-1), rel[..., 3])
    twist = torch.remainder(twist + math.pi, 2.0 * math.pi) - math.pi
    lo, hi = float(limits[0]), float(limits[1])
    return torch.minimum(torch.maximum(twist + turn, twist.clamp(max=lo)), twist.clamp(min=hi)) - twist


def _turn_t(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Unit quaternions turning by `angle` about unit `axis` (torch)."""
    import torch

    return torch.cat([torch.sin(0.5 * angle)[..., None] * axis, torch.cos(0.5 * angle)[..., None]], dim=-1)


def _rotation_between_t(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Smallest rotation carrying unit u onto v (torch); opposite vectors get an arbitrary answer."""
    import torch

    q = torch.cat([torch.linalg.cross(u, v), 1.0 + (u * v).sum(-1, keepdim=True)], dim=-1)
    return q / q.norm(dim=-1, keepdim=True).clamp_min(1e-8)


def split_evenly(
    parent: np.ndarray, child: np.ndarray, rest_parent: np.ndarray, rest_child: np.ndarray, share: float = 0.5
) -> tuple[np.ndarray, np.ndarray]:
    """A two-joint chain re-split from its composite, the parent taking `share`: no flips between them."""
    composite = quat_mul(parent, child)
    turn = quat_mul(composite, quat_inv(quat_mul(rest_parent, rest_child)))
    new_parent = quat_mul(quat_exp(share * quat_log(turn)), rest_parent)
    return new_parent, quat_mul(quat_inv(new_parent), composite)


def bone_axes(skeleton: Skeleton) -> np.ndarray:
    """(J, 3) unit axis each joint's twist turns about (its bone, End Site or own offset)."""
    axes = np.zeros((skeleton.num_joints, 3))
    for j in range(skeleton.num_joints):
        own = skeleton.offsets[j]
        kids = [skeleton.offsets[c] for c in skeleton.children(j) if np.linalg.norm(skeleton.offsets[c]) > 1e-6]
        end = skeleton.end_sites[j]
        if kids:
            unit_own = own / max(np.linalg.norm(own), 1e-9)
            axis = max(kids, key=lambda k: float(np.dot(k / np.linalg.norm(k), unit_own)))
        elif not np.isnan(end).any() and np.linalg.norm(end) > 1e-6:
            axis = end
        else:
            axis = own
        n = np.linalg.norm(axis)
        axes[j] = axis / n if n > 1e-9 else (1.0, 0.0, 0.0)
    return axes
