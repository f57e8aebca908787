"""Rotation conversions on arrays of any leading shape (numpy, via scipy).

Quaternions are scalar-last (x, y, z, w); matrices act on column vectors; Euler angles follow
BVH (intrinsic, in channel order: "ZXY" is Rz @ Rx @ Ry). Torch twins for training live in
`rotations_torch`, so numpy-only code never imports torch.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

# --------------------------------------------------------------------------- numpy (scipy)


def _flat(x: np.ndarray, tail: int) -> tuple[np.ndarray, tuple[int, ...]]:
    x = np.asarray(x, dtype=np.float64)
    return x.reshape(-1, *x.shape[x.ndim - tail :]), x.shape[: x.ndim - tail]


def euler_to_quat(angles_deg: np.ndarray, order: str) -> np.ndarray:
    """(..., 3) intrinsic Euler angles in degrees, in `order` (e.g. "ZXY") -> (..., 4)."""
    flat, lead = _flat(angles_deg, 1)
    return Rotation.from_euler(order.upper(), flat, degrees=True).as_quat().reshape(*lead, 4)


def quat_to_euler(quat: np.ndarray, order: str) -> np.ndarray:
    flat, lead = _flat(quat, 1)
    return Rotation.from_quat(flat).as_euler(order.upper(), degrees=True).reshape(*lead, 3)


def quat_to_matrix(quat: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions (normalised here) -> (..., 3, 3); plain numpy, cheap on small arrays."""
    q = np.asarray(quat, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    xx, yy, zz, xy, xz, yz, wx, wy, wz = x * x, y * y, z * z, x * y, x * z, y * z, w * x, w * y, w * z
    m = np.empty(q.shape[:-1] + (3, 3))
    m[..., 0, 0], m[..., 0, 1], m[..., 0, 2] = 1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy)
    m[..., 1, 0], m[..., 1, 1], m[..., 1, 2] = 2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx)
    m[..., 2, 0], m[..., 2, 1], m[..., 2, 2] = 2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)
    return m


def matrix_to_quat(mat: np.ndarray) -> np.ndarray:
    """(..., 3, 3) -> (..., 4) with w >= 0; Shepperd's method (stable everywhere)."""
    m = np.asarray(mat, dtype=np.float64)
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    trace = m00 + m11 + m22
    d21, d02, d10 = m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]
    s01, s02, s12 = m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1]
    cands = np.stack(
        [
            np.stack([d21, d02, d10, 1 + trace], -1),
            np.stack([1 + m00 - m11 - m22, s01, s02, d21], -1),
            np.stack([s01, 1 + m11 - m00 - m22, s12, d02], -1),
            np.stack([s02, s12, 1 + m22 - m00 - m11, d10], -1),
        ],
        axis=-2,
    )
    best = np.stack([trace, m00, m11, m22], -1).argmax(-1)
    q = np.take_along_axis(cands, best[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:] < 0, -q, q)


def quat_log(quat: np.ndarray) -> np.ndarray:
    """(..., 4) -> (..., 3) rotation vectors (axis * angle), shortest arc, angle in [0, pi]."""
    flat, lead = _flat(quat, 1)
    return Rotation.from_quat(flat).as_rotvec().reshape(*lead, 3)


def quat_exp(rotvec: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors -> (..., 4) unit quaternions; the inverse of `quat_log`."""
    flat, lead = _flat(rotvec, 1)
    return Rotation.from_rotvec(flat).as_quat().reshape(*lead, 4)


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b (apply b, then a), broadcasting; plain numpy (scipy's ~10 us a call)."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    ax, ay, az, aw = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bx, by, bz, bw = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return np.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        axis=-1,
    )


def quat_inv(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    return np.concatenate([-q[..., :3], q[..., 3:]], axis=-1)


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """np.cross for (..., 3) without its per-call overhead (which dominates on small arrays)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def quat_apply(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors v (..., 3) by unit quaternions q (..., 4), broadcasting leading axes."""
    q, v = np.asarray(q, float), np.asarray(v, float)
    xyz, w = q[..., :3], q[..., 3:]
    t = 2.0 * cross(xyz, v)
    return v + w * t + cross(xyz, t)


def quat_canonical(q: np.ndarray) -> np.ndarray:
    """Make quaternion signs temporally continuous along axis 0 (q and -q are one rotation)."""
    q = np.array(q, dtype=np.float64)
    dots = np.sum(q[1:] * q[:-1], axis=-1)
    flips = np.cumsum(dots < 0, axis=0) % 2
    q[1:][flips.astype(bool)] *= -1
    return q


def matrix_to_6d(mat: np.ndarray) -> np.ndarray:
    """The first two columns of a rotation matrix (Zhou et al. 2019), flattened to (..., 6)."""
    mat = np.asarray(mat, float)
    return np.concatenate([mat[..., :, 0], mat[..., :, 1]], axis=-1)


def quat_angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (radians, 0..pi) between unit quaternions a and b; sign-blind."""
    dot = np.abs(np.sum(np.asarray(a, float) * np.asarray(b, float), axis=-1))
    return 2.0 * np.arccos(np.clip(dot, 0.0, 1.0))


def twist_angle(q: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Signed twist angle of q about unit `axis` (radians): a bone's turn about itself."""
    q = np.asarray(q, float)
    along = np.sum(q[..., :3] * np.asarray(axis, float), axis=-1)
    return wrap_angle(2.0 * np.arctan2(along, q[..., 3]))


def swing_twist(q: np.ndarray, axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(swing, twist), q = swing * twist, twist about unit `axis`; a 180-degree swing: identity twist."""
    q = np.asarray(q, float)
    axis = np.asarray(axis, float)
    along = np.sum(q[..., :3] * axis, axis=-1, keepdims=True)
    twist = np.concatenate([along * axis, q[..., 3:]], axis=-1)
    norm = np.linalg.norm(twist, axis=-1, keepdims=True)
    identity = np.array([0.0, 0.0, 0.0, 1.0])
    twist = np.where(norm > 1e-9, twist / np.maximum(norm, 1e-12), identity)
    return quat_mul(q, quat_inv(twist)), twist


def yaw_quat(yaw: np.ndarray) -> np.ndarray:
    """(..., 4) rotation by `yaw` radians about +Y, in the input's float precision."""
    h = 0.5 * np.asarray(yaw)
    z = np.zeros_like(h)
    return np.stack([z, np.sin(h), z, np.cos(h)], axis=-1)


def rotate_y(v: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Vectors (..., 3), or ground-plane ones (..., 2) [x, z], rotated about +Y by yaw (...,)."""
    c, s = np.cos(yaw), np.sin(yaw)
    x, z = v[..., 0], v[..., -1]
    xz = [c * x + s * z, -s * x + c * z]
    return np.stack(xz if v.shape[-1] == 2 else [xz[0], v[..., 1], xz[1]], axis=-1)


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angles (radians) wrapped into [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def quat_mean(q: np.ndarray, axis: int = 0) -> np.ndarray:
    """Sign-blind mean rotation along `axis` (Markley et al. 2007), with w >= 0."""
    q = np.moveaxis(np.asarray(q, float), axis, -2)  # (..., N, 4)
    m = np.einsum("...ni,...nj->...ij", q, q)
    _, vecs = np.linalg.eigh(m)
    mean = vecs[..., :, -1]
    return np.where(mean[..., 3:] < 0, -mean, mean)
