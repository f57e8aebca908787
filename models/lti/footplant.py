"""Footplant annotation (Hsu et al. 2005, Sec. 5): Fisher's discriminant of the LTI state per foot,
with a Gaussian per class on the projection; its contacts are the planter's hints
(`models.motion.feet`). Training labels: an ankle within `HEIGHT_MARGIN` cm of the clip's lowest
and slower than `SPEED_LIMIT` cm/s on the ground.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

FEET = ("Foot_L", "Foot_R")
HEIGHT_MARGIN = 3.0
SPEED_LIMIT = 40.0


def contact_labels(positions: np.ndarray, skeleton, fps: float) -> np.ndarray:
    """World joint positions (F, J, 3) -> (F, 2) bool, ankle-based contacts."""
    out = np.zeros((len(positions), 2), bool)
    for k, name in enumerate(FEET):
        p = positions[:, skeleton.index(name)]
        v = np.linalg.norm(np.gradient(p[:, [0, 2]], axis=0), axis=1) * fps if len(p) > 1 else np.zeros(len(p))
        out[:, k] = (p[:, 1] < p[:, 1].min() + HEIGHT_MARGIN) & (v < SPEED_LIMIT)
    return out


@dataclass
class FootplantClassifier:
    w: np.ndarray  # (n, 2) projection per foot
    mean: np.ndarray  # (2 feet, 2 classes) mean of the projection
    var: np.ndarray  # (2, 2)
    log_prior: np.ndarray  # (2, 2)

    @classmethod
    def fit(cls, states: np.ndarray, labels: np.ndarray, ridge: float = 1e-3) -> FootplantClassifier:
        n = states.shape[1]
        W = np.zeros((n, 2))
        mean, var, prior = np.zeros((2, 2)), np.ones((2, 2)), np.full((2, 2), np.log(0.5))
        for k in range(2):
            cls_x = [states[~labels[:, k]], states[labels[:, k]]]
            if min(len(c) for c in cls_x) < 2 or n == 0:
                continue
            mus = [c.mean(0) for c in cls_x]
            Sw = sum(np.cov(c, rowvar=False) * (len(c) - 1) for c in cls_x) / len(states)
            Sw += ridge * np.trace(Sw) / n * np.eye(n)
            w = np.linalg.solve(Sw, mus[1] - mus[0])
            w /= np.linalg.norm(w)
            W[:, k] = w
            for c in range(2):
                s = cls_x[c] @ w
                mean[k, c], var[k, c] = s.mean(), max(s.var(), 1e-8)
                prior[k, c] = np.log(len(s) / len(states))
        return cls(W, mean, var, prior)

    def predict(self, states: np.ndarray) -> np.ndarray:
        """(..., n) -> (..., 2) bool: the more likely Gaussian class of the projected state."""
        s = (states @ self.w)[..., None]  # (..., 2, 1)
        ll = -0.5 * (s - self.mean) ** 2 / self.var - 0.5 * np.log(self.var) + self.log_prior
        return ll[..., 1] > ll[..., 0]

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {"fp_w": self.w, "fp_mean": self.mean, "fp_var": self.var, "fp_prior": self.log_prior}

    @classmethod
    def from_arrays(cls, z) -> FootplantClassifier:
        return cls(z["fp_w"], z["fp_mean"], z["fp_var"], z["fp_prior"])
