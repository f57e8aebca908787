"""The one home of quaternion maths inside compiled kernels (numba), on 4-tuples (x, y, z, w),
float64: tuples read well (`qmul(qinv(a), b)`) and numba inlines them. `models/numba_cache.py`
keys the cache by every kernel source, so importing them is cache-safe. Array maths: `rotations.py`.
"""

from __future__ import annotations

import math

from numba import njit


@njit(cache=True, error_model="numpy")
def qmul(a, b):
    """Hamilton product a * b (apply b, then a)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    )


@njit(cache=True, error_model="numpy")
def qinv(q):
    """Inverse of a unit quaternion (its conjugate)."""
    return (-q[0], -q[1], -q[2], q[3])


@njit(cache=True, error_model="numpy")
def qunit(q):
    """q scaled to unit length."""
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


@njit(cache=True, error_model="numpy")
def qscale(q, k):
    """k q, each component scaled."""
    return (k * q[0], k * q[1], k * q[2], k * q[3])


@njit(cache=True, error_model="numpy")
def qdot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3]


@njit(cache=True, error_model="numpy")
def qneg(q):
    """The same rotation from the other hemisphere."""
    return (-q[0], -q[1], -q[2], -q[3])


@njit(cache=True, error_model="numpy")
def cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


@njit(cache=True, error_model="numpy")
def dot3(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@njit(cache=True, error_model="numpy")
def add3(a, b):
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


@njit(cache=True, error_model="numpy")
def sub3(a, b):
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


@njit(cache=True, error_model="numpy")
def qrot(q, v):
    """Rotate vector v by unit quaternion q (two cross products, no matrix)."""
    xyz = (q[0], q[1], q[2])
    t = cross(xyz, v)
    t = (2.0 * t[0], 2.0 * t[1], 2.0 * t[2])
    u = cross(xyz, t)
    w = q[3]
    return (v[0] + w * t[0] + u[0], v[1] + w * t[1] + u[1], v[2] + w * t[2] + u[2])


@njit(cache=True, error_model="numpy")
def qlog(q):
    """Rotation vector (axis * angle) of a unit quaternion, along the shortest arc."""
    x, y, z, w = q
    if w < 0.0:
        x, y, z, w = -x, -y, -z, -w
    s = math.sqrt(x * x + y * y + z * z)
    if s <= 1e-9:
        return (2.0 * x, 2.0 * y, 2.0 * z)
    k = 2.0 * math.atan2(s, w) / s
    return (k * x, k * y, k * z)


@njit(cache=True, error_model="numpy")
def qexp(v):
    """Unit quaternion of a rotation vector; the inverse of `qlog`."""
    a = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    k = math.sin(0.5 * a) / a if a > 1e-9 else 0.5
    return (k * v[0], k * v[1], k * v[2], math.cos(0.5 * a))


@njit(cache=True, error_model="numpy")
def qyaw(yaw):
    """Unit quaternion turning by `yaw` radians about +Y (up)."""
    return (0.0, math.sin(0.5 * yaw), 0.0, math.cos(0.5 * yaw))


@njit(cache=True, error_model="numpy")
def turn_y(x, z, c, s):
    """Ground-plane vector (x, z) turned about +Y by the yaw of cosine c and sine s; (c, -s) turns back."""
    return c * x + s * z, -s * x + c * z


@njit(cache=True, error_model="numpy")
def nlerp(a, t, share):
    """(1 - share) a + share t, normalised, with t taken on a's hemisphere."""
    if qdot(t, a) < 0.0:
        t = qneg(t)
    return qunit(
        (
            (1.0 - share) * a[0] + share * t[0],
            (1.0 - share) * a[1] + share * t[1],
            (1.0 - share) * a[2] + share * t[2],
            (1.0 - share) * a[3] + share * t[3],
        )
    )


@njit(cache=True, error_model="numpy")
def axis_angle(axis, angle):
    """Unit quaternion turning by `angle` radians about the unit vector `axis`."""
    s = math.sin(0.5 * angle)
    return (s * axis[0], s * axis[1], s * axis[2], math.cos(0.5 * angle))


@njit(cache=True, error_model="numpy")
def between(u, v):
    """Shortest-arc unit quaternion carrying unit u onto unit v (any perpendicular axis if opposite)."""
    d = dot3(u, v)
    c = cross(u, v)
    q = (c[0], c[1], c[2], 1.0 + d)
    if q[3] < 1e-9:
        ax = (0.0, u[2], -u[1])  # u x (1, 0, 0)
        if ax[1] * ax[1] + ax[2] * ax[2] < 1e-12:
            ax = (-u[2], 0.0, u[0])  # u x (0, 1, 0)
        q = (ax[0], ax[1], ax[2], 0.0)
    return qunit(q)


@njit(cache=True, error_model="numpy")
def quat_at(a, i, j):
    """Quaternion a[i, j] of a (n, m, 4) array as a 4-tuple."""
    return (a[i, j, 0], a[i, j, 1], a[i, j, 2], a[i, j, 3])


@njit(cache=True, error_model="numpy")
def row4(a, j):
    """Row j of an (n, 4) array as a 4-tuple."""
    return (a[j, 0], a[j, 1], a[j, 2], a[j, 3])


@njit(cache=True, error_model="numpy")
def row3(a, j):
    """Row j of an (n, 3) array as a 3-tuple."""
    return (a[j, 0], a[j, 1], a[j, 2])


@njit(cache=True, error_model="numpy")
def wrap(a):
    """Angle a wrapped into [-pi, pi)."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@njit(cache=True, error_model="numpy")
def matrix_quat(m):
    """Unit quaternion of a 3x3 rotation matrix (Markley 2008, as scipy's `Rotation.from_matrix`)."""
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    best, k = m[0, 0], 0
    if m[1, 1] > best:
        best, k = m[1, 1], 1
    if m[2, 2] > best:
        best, k = m[2, 2], 2
    if tr > best:
        k = 3
    if k == 0:
        q = (1.0 - tr + 2.0 * m[0, 0], m[1, 0] + m[0, 1], m[2, 0] + m[0, 2], m[2, 1] - m[1, 2])
    elif k == 1:
        q = (m[1, 0] + m[0, 1], 1.0 - tr + 2.0 * m[1, 1], m[2, 1] + m[1, 2], m[0, 2] - m[2, 0])
    elif k == 2:
        q = (m[2, 0] + m[0, 2], m[2, 1] + m[1, 2], 1.0 - tr + 2.0 * m[2, 2], m[1, 0] - m[0, 1])
    else:
        q = (m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1], 1.0 + tr)
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)
