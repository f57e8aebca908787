"""An LTI system simulated in numpy from rest: the reference the identification tests
(`models/lti/subspace.py`) compare with."""

from __future__ import annotations

import numpy as np


def simulate(A, B, C, D, u: np.ndarray) -> np.ndarray:
    """(F, p) outputs y[t] = C x[t] + D u[t] of inputs u (F, m), with x[t+1] = A x[t] + B u[t]."""
    x = np.zeros(A.shape[0])
    y = np.empty((len(u), C.shape[0]))
    for t in range(len(u)):
        y[t] = C @ x + D @ u[t]
        x = A @ x + B @ u[t]
    return y
