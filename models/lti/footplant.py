"""Footplant annotation (Hsu et al. 2005, Sec. 5): a one-dimensional multiple discriminant
analysis (two classes: Fisher's discriminant) of the LTI state per foot, with a Gaussian per
class on the projection; plus a simple foot lock (two-bone leg IK) driven by the predicted contacts.

Labels for training come from the (time-warped) output examples: a foot (ankle joint) is planted
when it is within `HEIGHT_MARGIN` cm of the clip's lowest ankle height and moves slower than
`SPEED_LIMIT` cm/s on the ground plane.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import kernels

FEET = ("Foot_L", "Foot_R")
LEG_CHAINS = (("UpperLeg_L", "LowerLeg_L", "Foot_L"), ("UpperLeg_R", "LowerLeg_R", "Foot_R"))
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


def two_bone_ik(gh: np.ndarray, r_up: np.ndarray, r_low: np.ndarray, r_foot: np.ndarray,
                a: np.ndarray, off_low: np.ndarray, off_foot: np.ndarray, target: np.ndarray):
    """Analytic two-bone IK for a batch of legs (`kernels.two_bone_ik`). gh: (B, 4) world rotation
    of the parent (Hips); r_*: (B, 4) local rotations of UpperLeg, LowerLeg, Foot; a: (B, 3) world
    hip-joint position; off_*: bone offsets. Returns new local (r_up, r_low, r_foot) putting the
    ankle at `target` (as close as the bone lengths allow) with the foot's world orientation unchanged."""
    f64 = lambda v: np.ascontiguousarray(v, dtype=np.float64)
    return kernels.two_bone_ik_batch(f64(gh), f64(r_up), f64(r_low), f64(r_foot), f64(a), f64(off_low),
                                     f64(off_foot), f64(target))


class FootLock:
    """Per-session foot lock by two-bone leg IK: when a foot becomes planted its ankle position is
    anchored, and while it stays planted the leg is bent so the ankle stays on the anchor; after
    release the target follows the animated ankle again over `release_frames` frames. The root
    (and so the path) is not changed. The anchor never lags the animated ankle by more than
    `max_pull` cm (it is dragged along): the translated root tends to outpace the translated
    strides, and an unbounded lock would straighten the knees, erasing e.g. the elderly bent knee.
    Needs only the leg chains' forward kinematics. The work is done per session by
    `kernels.foot_lock_session`, which the streaming step also calls."""

    def __init__(self, skeleton, batch: int, release_frames: int = 4, max_pull: float = 5.0):
        self.chains = np.array([[skeleton.index(n) for n in chain] for chain in LEG_CHAINS], dtype=np.int64)
        self.offsets = np.ascontiguousarray(skeleton.offsets, dtype=np.float64)
        self.release = release_frames
        self.max_pull = max_pull  # cm: the anchor is dragged along when the animated ankle gets farther
        self.anchor = np.zeros((batch, 2, 3))
        self.since = np.full((batch, 2), 10**6, dtype=np.int64)  # frames since the last planted frame
        self.was = np.zeros((batch, 2), bool)

    def params(self) -> tuple[np.ndarray, np.ndarray, int, float]:
        """(chains, offsets, release_frames, max_pull) as the kernels take them."""
        return self.chains, self.offsets, self.release, self.max_pull

    def foot_positions(self, root: np.ndarray, rotations: np.ndarray) -> np.ndarray:
        """(B, 3), (B, J, 4) -> (B, 2 feet, 3) ankle world positions (joint_Root is identity)."""
        return kernels.ankle_positions(np.ascontiguousarray(root, dtype=np.float64),
                                       np.ascontiguousarray(rotations, dtype=np.float64), self.chains, self.offsets)

    def __call__(self, root: np.ndarray, rotations: np.ndarray, contacts: np.ndarray) -> np.ndarray:
        """Returns the rotations with the IK applied (a new array); updates the lock state."""
        out = np.array(rotations, dtype=np.float64, order="C")
        kernels.foot_lock(np.ascontiguousarray(root, dtype=np.float64), out, np.ascontiguousarray(contacts, dtype=bool),
                          self.anchor, self.since, self.was, *self.params())
        return out
