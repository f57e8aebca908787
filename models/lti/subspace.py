"""Subspace identification of discrete LTI systems  x[t+1] = A x[t] + B u[t],  y[t] = C x[t] + D u[t].

Not a PyPI package: `nfoursid` and SIPPY take one record (here: hundreds of clip pairs) and fit
B/D for one-step prediction, not simulation from x0 = 0. PO-MOESP (Verhaegen 1994) over stacked
block-Hankel matrices gives the observability matrix; C is its first block row, A follows by shift
invariance and is made stable; B and D are least squares of the simulated output, plus the
expected output energy of an assumed input noise (`noise_energy`): large cancelling gains on
correlated inputs would amplify a live stream's noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla


@dataclass
class StateSpace:
    A: np.ndarray  # (n, n)
    B: np.ndarray  # (n, m)
    C: np.ndarray  # (p, n)
    D: np.ndarray  # (p, m)
    raw_radius: float = 0.0  # spectral radius of A as identified, before `stabilize`
    n_stabilized: int = 0  # eigenvalues moved by `stabilize`

    @property
    def order(self) -> int:
        return self.A.shape[0]


def spectral_radius(A: np.ndarray) -> float:
    return float(np.max(np.abs(np.linalg.eigvals(A)))) if A.size else 0.0


def stabilize(A: np.ndarray, max_radius: float = 0.995) -> tuple[np.ndarray, int]:
    """Reflect eigenvalues inside the unit circle, cap at `max_radius`: (A, eigenvalues changed)."""
    if A.size == 0:
        return A, 0
    lam, V = np.linalg.eig(A)
    mod = np.abs(lam)
    bad = mod >= max_radius
    if not bad.any():
        return A, 0
    new = lam.copy()
    new[bad] = lam[bad] / mod[bad] * np.minimum(1.0 / mod[bad], max_radius)
    A2 = np.real(V @ np.diag(new) @ np.linalg.inv(V))
    if spectral_radius(A2) >= 1.0:  # defective/ill-conditioned eigenvectors: fall back to scaling
        A2 = A * (max_radius / spectral_radius(A))
    return A2, int(bad.sum())


def _hankel(x: np.ndarray, start: int, rows: int, cols: int) -> np.ndarray:
    """Block Hankel: block row r holds x[start + r : start + r + cols].T -> (rows * dim, cols)."""
    return np.concatenate([x[start + r : start + r + cols].T for r in range(rows)], axis=0)


def choose_order(sv: np.ndarray, max_order: int, energy: float = 0.99, gap: float = 1e3) -> int:
    """Order at an obvious gap (> `gap`), else keeping `energy` of the squared values; <= `max_order`."""
    sv = np.asarray(sv, float)
    k = min(max_order, len(sv) - 1)
    if k <= 0 or sv[0] <= 0:
        return 0
    ratios = sv[:k] / np.maximum(sv[1 : k + 1], 1e-300)
    big = np.flatnonzero(ratios > gap)
    if big.size:
        return int(big[0] + 1)
    cum = np.cumsum(sv**2) / np.sum(sv**2)
    return min(k, int(np.searchsorted(cum, energy)) + 1)


def subspace_id(
    records: list[tuple[np.ndarray, np.ndarray]], horizon: int = 10,
    order: int | None = None, max_order: int = 20, energy: float = 0.99,  # the state dimension: given, or by energy
    max_radius: float = 0.995, ridge: float = 1e-6, input_noise: np.ndarray | None = None,
) -> StateSpace:  # fmt: skip
    """Identify (A, B, C, D) from records (u (T, m), y (T, p)); `horizon`: Hankel block rows."""
    i = horizon
    m = records[0][0].shape[1]
    p = records[0][1].shape[1]
    blocks = []
    for u, y in records:
        cols = len(u) - 2 * i + 1
        if cols <= 0:
            continue
        blocks.append(
            np.concatenate(
                [
                    _hankel(u, i, i, cols),  # U_f
                    _hankel(u, 0, i, cols),  # U_p
                    _hankel(y, 0, i, cols),  # Y_p
                    _hankel(y, i, i, cols),  # Y_f
                ],
                axis=0,
            )
        )
    if not blocks:
        raise ValueError("records are too short for the chosen horizon")
    rows = 2 * i * (m + p)
    gram = np.zeros((rows, rows))
    ncols = 0
    for H in blocks:
        gram += H @ H.T
        ncols += H.shape[1]
    gram /= ncols
    jitter = 1e-10 * np.trace(gram) / rows
    L = np.linalg.cholesky(gram + jitter * np.eye(rows))  # gram = L L^T, i.e. H = L Q
    a, b = m * i, m * i + (m + p) * i
    L32 = L[b:, a:b]
    U, sv, _ = np.linalg.svd(L32, full_matrices=False)
    n = choose_order(sv, max_order, energy) if order is None else order
    if n == 0:
        A, C = np.zeros((0, 0)), np.zeros((p, 0))
    else:
        gamma = U[:, :n] * np.sqrt(sv[:n])
        C = gamma[:p]
        A = np.linalg.lstsq(gamma[:-p], gamma[p:], rcond=None)[0]
    raw = spectral_radius(A)
    A, changed = stabilize(A, max_radius)
    B, D = fit_bd(A, C, records, ridge, input_noise)
    return StateSpace(A, B, C, D, raw_radius=raw, n_stabilized=changed)


def fit_bd(
    A: np.ndarray,
    C: np.ndarray,
    records: list[tuple[np.ndarray, np.ndarray]],
    ridge: float = 1e-6,
    input_noise: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares B, D for simulation from x0 = 0 (A, C fixed), plus the expected error of white
    noise input_noise[j] on each input. x_t = sum_j V_t^(j) b_j, V_{t+1}^(j) = A V_t^(j) + u_t[j] I;
    unknowns [vec(B^T) (j-major), vec(D) (row-major)]."""
    n, p, m = A.shape[0], C.shape[0], records[0][0].shape[1]
    nb, nd = n * m, p * m
    G = np.zeros((nb + nd, nb + nd))
    h = np.zeros(nb + nd)
    eye = np.eye(n)
    for u, y in records:
        T = len(u)
        phi = np.zeros((T, p, nb + nd))
        if n:
            V = np.zeros((m, n, n))
            for t in range(T):
                phi[t, :, :nb] = np.einsum("pn,jnr->pjr", C, V).reshape(p, nb)
                V = A @ V + u[t][:, None, None] * eye
        for k in range(p):
            phi[:, k, nb + k * m : nb + (k + 1) * m] = u
        phi = phi.reshape(T * p, nb + nd)
        G += phi.T @ phi
        h += phi.T @ y.reshape(T * p)
    if input_noise is not None and np.any(input_noise):
        G += noise_energy(A, C, np.asarray(input_noise, float), sum(len(u) for u, _ in records))
    G[np.diag_indices_from(G)] += ridge * max(1.0, np.trace(G) / len(G))
    theta = sla.solve(G, h, assume_a="pos")
    B = theta[:nb].reshape(m, n).T
    D = theta[nb:].reshape(p, m)
    return B, D


def noise_energy(A: np.ndarray, C: np.ndarray, sigma: np.ndarray, frames: int) -> np.ndarray:
    """fit_bd's quadratic form: frames sigma_j^2 (b_j^T W_o b_j + ||d_j||^2), W_o the observability Gramian."""
    n, p, m = A.shape[0], C.shape[0], len(sigma)
    nb = n * m
    out = np.zeros((nb + p * m, nb + p * m))
    w = frames * sigma**2
    if n:
        gram = sla.solve_discrete_lyapunov(A.T, C.T @ C)
        for j in range(m):
            out[j * n : (j + 1) * n, j * n : (j + 1) * n] = w[j] * gram
    d = nb + np.arange(p * m)
    out[d, d] = np.tile(w, p)  # D[k, j] sits at nb + k * m + j
    return out
