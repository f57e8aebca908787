"""Correspondence between an input-style clip and an output-style clip of the same content.

`imw` is Hsu et al.'s iterative motion warping: a time warp w and a per-DOF space warp (scale a_t,
offset b_t) minimising

    E = sum_t |x_t - a_t * y(w(t)) - b_t|^2
        + lam * sum_t (|a_{t+1} - a_t|^2 + |b_{t+1} - b_t|^2)     (first-difference smoothness)
        + mu  * sum_t (|a_t - 1|^2 + |b_t|^2)                     (keeps the warp near identity)

by alternating exact minimisations: time by dynamic programming over monotone warps (slopes in
[1/s, max_step/s]), space by a sparse banded system per DOF. Training keeps only the time warp.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla


@dataclass
class WarpResult:
    warp: np.ndarray  # (T,) output time (in output frames, fractional) for each input frame
    scale: np.ndarray  # (T, D)
    offset: np.ndarray  # (T, D)
    objective: list[float] = field(default_factory=list)  # E after every stage (time, space, time, ...)


def upsample(y: np.ndarray, s: int) -> np.ndarray:
    """Linear interpolation at times k/s, k = 0 .. s*(U-1)."""
    u = len(y)
    t = np.arange(s * (u - 1) + 1) / s
    i0 = np.minimum(np.floor(t).astype(int), u - 2) if u > 1 else np.zeros(len(t), int)
    f = (t - i0)[:, None]
    return y[i0] * (1 - f) + y[np.minimum(i0 + 1, u - 1)] * f


def time_warp_dp(cost: np.ndarray, max_step: int, step_cost: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """Minimum-cost monotone path through `cost` (T, K), rows advancing 1..max_step columns."""
    T, K = cost.shape
    acc = np.full((T, K), np.inf)
    back = np.zeros((T, K), np.int8)
    acc[0, 0] = cost[0, 0]
    extra = np.zeros(max_step) if step_cost is None else step_cost
    for t in range(1, T):
        prev = acc[t - 1]
        cands = np.full((max_step, K), np.inf)
        for k in range(1, max_step + 1):
            cands[k - 1, k:] = prev[:-k] + extra[k - 1]
        best = np.argmin(cands, axis=0)
        acc[t] = cost[t] + cands[best, np.arange(K)]
        back[t] = best + 1
    if not np.isfinite(acc[-1, -1]):
        raise ValueError(f"no warp with slope limits fits lengths {T} -> {K}")
    path = np.empty(T, int)
    path[-1] = K - 1
    for t in range(T - 1, 0, -1):
        path[t - 1] = path[t] - back[t, path[t]]
    return path, float(acc[-1, -1])


def _space_system(T: int, lam: float, mu: float) -> sp.csc_matrix:
    diff = sp.diags([-np.ones(T - 1), np.ones(T - 1)], [0, 1], shape=(T - 1, T))
    return (lam * (diff.T @ diff) + mu * sp.eye(T)).tocsc()


def space_warp(x: np.ndarray, yw: np.ndarray, lam: float, mu: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-DOF smooth scale/offset from the normal equations, in one sparse factorisation."""
    T, D = x.shape
    R = sp.kron(sp.eye(D), _space_system(T, lam, mu))
    y, xd = yw.T.ravel(), x.T.ravel()  # DOF-major
    Y = sp.diags(y)
    system = sp.bmat([[sp.diags(y * y) + R, Y], [Y, sp.eye(T * D) + R]], format="csc")
    sol = spla.spsolve(system, np.concatenate([y * xd + mu, xd]), permc_spec="MMD_AT_PLUS_A")
    sol = sol.reshape(2, D, T)
    return sol[0].T, sol[1].T


def objective(x: np.ndarray, yw: np.ndarray, a: np.ndarray, b: np.ndarray, lam: float, mu: float) -> float:
    data = np.sum((x - a * yw - b) ** 2)
    smooth = lam * (np.sum(np.diff(a, axis=0) ** 2) + np.sum(np.diff(b, axis=0) ** 2))
    reg = mu * (np.sum((a - 1) ** 2) + np.sum(b**2))
    return float(data + smooth + reg)


def imw(
    x: np.ndarray, y: np.ndarray,
    s: int = 3, max_step: int = 6,  # slopes in [1/s, max_step/s]
    lam: float = 10.0, mu: float = 0.1,  # the space warp's smoothness and pull toward identity
    max_iter: int = 10, tol: float = 1e-4, rate_weight: float = 0.0,
) -> WarpResult:  # fmt: skip
    """Warp output y (U, D) onto input x (T, D); `rate_weight` charges uneven slopes (else: staircases)."""
    T, D = x.shape
    yu = upsample(y, s)
    ks = np.arange(1, max_step + 1)
    mean_step = (len(yu) - 1) / max(T - 1, 1)
    step_cost = rate_weight * D * ((ks - mean_step) / s) ** 2 if rate_weight > 0 else None

    def charged(p: np.ndarray) -> float:  # the warp's rate charge, part of E when there is one
        return 0.0 if step_cost is None else float(step_cost[np.diff(p) - 1].sum())

    a, b = np.ones((T, D)), np.zeros((T, D))
    history: list[float] = []
    path = np.zeros(T, np.int64)
    for _ in range(max_iter):
        # time stage: cost[t, k] = |x_t - b_t - a_t * yu_k|^2
        xb = x - b
        cost = np.sum(xb * xb, axis=1)[:, None] - 2.0 * (xb * a) @ yu.T + (a * a) @ (yu * yu).T
        new_path, _ = time_warp_dp(np.maximum(cost, 0.0), max_step, step_cost)
        e_time = objective(x, yu[new_path], a, b, lam, mu) + charged(new_path)
        if history and e_time > history[-1]:  # cannot happen (DP is exact); guard round-off
            break
        path = new_path
        history.append(e_time)
        # space stage
        a2, b2 = space_warp(x, yu[path], lam, mu)
        e_space = objective(x, yu[path], a2, b2, lam, mu) + charged(path)
        if e_space <= history[-1]:
            a, b = a2, b2
            history.append(e_space)
        if len(history) >= 3 and history[-3] - history[-1] <= tol * abs(history[-3]):
            break
    return WarpResult(path / s, a, b, history)


# --------------------------------------------------------------------------- resampling motions


def resample_pose(root: np.ndarray, rotations: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Root (U, 3) and rotations (U, J, 4) at fractional frame times: lerp / nlerp."""
    U = len(root)
    times = np.clip(times, 0, U - 1)
    i0 = np.minimum(np.floor(times).astype(int), max(U - 2, 0))
    i1 = np.minimum(i0 + 1, U - 1)
    f = times - i0
    r = root[i0] * (1 - f)[:, None] + root[i1] * f[:, None]
    q0, q1 = rotations[i0], rotations[i1]
    sign = np.where(np.sum(q0 * q1, -1, keepdims=True) < 0, -1.0, 1.0)
    q = q0 * (1 - f)[:, None, None] + sign * q1 * f[:, None, None]
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return r, q
