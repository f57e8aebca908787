"""The differentiable torch twins of `rotations` (same conventions: scalar-last quaternions,
matrices on column vectors, intrinsic BVH Euler orders), for training losses and forward
kinematics; each is tested against scipy. Kept apart so that numpy-only code never imports torch.
"""

from __future__ import annotations

import torch


def quat_to_matrix_t(q: torch.Tensor) -> torch.Tensor:
    """(..., 4) scalar-last quaternions (need not be unit) -> (..., 3, 3)."""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    x, y, z, w = q.unbind(-1)
    xx, yy, zz, xy, xz, yz, wx, wy, wz = x * x, y * y, z * z, x * y, x * z, y * z, w * x, w * y, w * z
    rows = [
        1 - 2 * (yy + zz),
        2 * (xy - wz),
        2 * (xz + wy),
        2 * (xy + wz),
        1 - 2 * (xx + zz),
        2 * (yz - wx),
        2 * (xz - wy),
        2 * (yz + wx),
        1 - 2 * (xx + yy),
    ]
    return torch.stack(rows, dim=-1).reshape(*q.shape[:-1], 3, 3)


def matrix_to_quat_t(m: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) -> (..., 4) scalar-last, w >= 0; branch on the largest diagonal term for stability."""
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    trace = m00 + m11 + m22
    cands = torch.stack(
        [
            torch.stack(
                [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1], 1 + trace], -1
            ),
            torch.stack(
                [
                    1 + m00 - m11 - m22,
                    m[..., 0, 1] + m[..., 1, 0],
                    m[..., 0, 2] + m[..., 2, 0],
                    m[..., 2, 1] - m[..., 1, 2],
                ],
                -1,
            ),
            torch.stack(
                [
                    m[..., 0, 1] + m[..., 1, 0],
                    1 + m11 - m00 - m22,
                    m[..., 1, 2] + m[..., 2, 1],
                    m[..., 0, 2] - m[..., 2, 0],
                ],
                -1,
            ),
            torch.stack(
                [
                    m[..., 0, 2] + m[..., 2, 0],
                    m[..., 1, 2] + m[..., 2, 1],
                    1 + m22 - m00 - m11,
                    m[..., 1, 0] - m[..., 0, 1],
                ],
                -1,
            ),
        ],
        dim=-2,
    )
    best = torch.stack([trace, m00, m11, m22], -1).argmax(-1)
    q = torch.gather(cands, -2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    return torch.where(q[..., 3:] < 0, -q, q)


def quat_mul_t(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    ax, ay, az, aw = a.unbind(-1)
    bx, by, bz, bw = b.unbind(-1)
    return torch.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        dim=-1,
    )


def quat_apply_t(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    xyz, w = q[..., :3], q[..., 3:]
    t = 2.0 * torch.cross(xyz, v, dim=-1)
    return v + w * t + torch.cross(xyz, t, dim=-1)


def expmap_to_quat_t(r: torch.Tensor) -> torch.Tensor:
    """Rotation vectors -> quaternions; the series form keeps gradients finite at angle 0."""
    angle = r.norm(dim=-1, keepdim=True)
    half = 0.5 * angle
    small = angle < 1e-4
    safe = torch.where(small, torch.ones_like(angle), angle)
    scale = torch.where(small, 0.5 - angle**2 / 48.0, torch.sin(half) / safe)
    return torch.cat([r * scale, torch.cos(half)], dim=-1)


def quat_to_expmap_t(q: torch.Tensor) -> torch.Tensor:
    q = torch.where(q[..., 3:] < 0, -q, q)
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    sin_half = q[..., :3].norm(dim=-1, keepdim=True)
    angle = 2.0 * torch.atan2(sin_half, q[..., 3:])
    small = sin_half < 1e-6
    scale = torch.where(
        small, 2.0 / q[..., 3:].clamp_min(1e-8), angle / torch.where(small, torch.ones_like(sin_half), sin_half)
    )
    return q[..., :3] * scale


def euler_to_matrix_t(angles_deg: torch.Tensor, order: str) -> torch.Tensor:
    """Intrinsic Euler (degrees) in `order` -> matrices, R = R_order[0] @ R_order[1] @ R_order[2]."""
    rad = torch.deg2rad(angles_deg)
    out = None
    for k, axis in enumerate(order.upper()):
        c, s = torch.cos(rad[..., k]), torch.sin(rad[..., k])
        one, zero = torch.ones_like(c), torch.zeros_like(c)
        if axis == "X":
            m = [one, zero, zero, zero, c, -s, zero, s, c]
        elif axis == "Y":
            m = [c, zero, s, zero, one, zero, -s, zero, c]
        else:
            m = [c, -s, zero, s, c, zero, zero, zero, one]
        mat = torch.stack(m, -1).reshape(*c.shape, 3, 3)
        out = mat if out is None else out @ mat
    return out


def sixd_to_matrix_t(d6: torch.Tensor) -> torch.Tensor:
    """(..., 6) -> rotation matrices by Gram-Schmidt, differentiable."""
    a1, a2 = d6[..., :3], d6[..., 3:]
    b1 = torch.nn.functional.normalize(a1, dim=-1)
    b2 = torch.nn.functional.normalize(a2 - (b1 * a2).sum(-1, keepdim=True) * b1, dim=-1)
    b3 = torch.cross(b1, b2, dim=-1)
    return torch.stack([b1, b2, b3], dim=-1)
