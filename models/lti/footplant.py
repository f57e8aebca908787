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

from models.motion.rotations import cross, quat_apply, quat_mul, quat_to_matrix

from . import representation as rep

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


def _nrm(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-9)


def _axis_angle(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    h = 0.5 * angle[..., None]
    return np.concatenate([_nrm(axis) * np.sin(h), np.cos(h)], axis=-1)


def _rotation_between(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Shortest-arc quaternion taking direction u to direction v."""
    u, v = _nrm(u), _nrm(v)
    q = np.concatenate([cross(u, v), 1.0 + np.sum(u * v, -1, keepdims=True)], axis=-1)
    return q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), 1e-12)


def two_bone_ik(gh: np.ndarray, r_up: np.ndarray, r_low: np.ndarray, r_foot: np.ndarray,
                a: np.ndarray, off_low: np.ndarray, off_foot: np.ndarray, target: np.ndarray):
    """Analytic two-bone IK for a leg. gh: (B, 4) world rotation of the parent (Hips); r_*: (B, 4)
    local rotations of UpperLeg, LowerLeg, Foot; a: (B, 3) world hip-joint position; off_*: bone
    offsets. Returns new local (r_up, r_low, r_foot) putting the ankle at `target` (as close as the
    bone lengths allow) with the foot's world orientation unchanged."""
    ga = quat_mul(gh, r_up)
    gb = quat_mul(ga, r_low)
    gf = quat_mul(gb, r_foot)
    b = a + quat_apply(ga, np.broadcast_to(off_low, a.shape))
    c = b + quat_apply(gb, np.broadcast_to(off_foot, a.shape))
    lab, lcb = np.linalg.norm(off_low, axis=-1), np.linalg.norm(off_foot, axis=-1)
    lat = np.clip(np.linalg.norm(target - a, axis=-1), 1e-3, lab + lcb - 1e-3)
    cos = lambda u, v: np.clip(np.sum(_nrm(u) * _nrm(v), -1), -1.0, 1.0)
    ac_ab_0, ba_bc_0 = np.arccos(cos(c - a, b - a)), np.arccos(cos(a - b, c - b))
    ac_ab_1 = np.arccos(np.clip((lcb**2 - lab**2 - lat**2) / (-2 * lab * lat), -1, 1))
    ba_bc_1 = np.arccos(np.clip((lat**2 - lab**2 - lcb**2) / (-2 * lab * lcb), -1, 1))
    axis = cross(c - a, b - a)
    # bend: rotate the thigh and the knee about the leg plane's normal (world), then swing
    w0 = _axis_angle(axis, ac_ab_1 - ac_ab_0)
    w1 = _axis_angle(axis, ba_bc_1 - ba_bc_0)
    ga2 = quat_mul(w0, ga)
    gb2 = quat_mul(w1, quat_mul(ga2, r_low))
    b2 = a + quat_apply(ga2, np.broadcast_to(off_low, a.shape))
    c2 = b2 + quat_apply(gb2, np.broadcast_to(off_foot, a.shape))
    w2 = _rotation_between(c2 - a, target - a)
    ga3 = quat_mul(w2, ga2)
    gb3 = quat_mul(w2, gb2)
    inv = rep.qinv
    return quat_mul(inv(gh), ga3), quat_mul(inv(ga3), gb3), quat_mul(inv(gb3), gf)


class FootLock:
    """Per-session foot lock by two-bone leg IK: when a foot becomes planted its ankle position is
    anchored, and while it stays planted the leg is bent so the ankle stays on the anchor; after
    release the target follows the animated ankle again over `release_frames` frames. The root
    (and so the path) is not changed. The anchor never lags the animated ankle by more than
    `max_pull` cm (it is dragged along): the translated root tends to outpace the translated
    strides, and an unbounded lock would straighten the knees, erasing e.g. the elderly bent knee. Needs only the leg chains' forward kinematics."""

    def __init__(self, skeleton, batch: int, release_frames: int = 4, max_pull: float = 5.0):
        self.chains = [[skeleton.index(n) for n in chain] for chain in LEG_CHAINS]
        self.offsets = skeleton.offsets
        self.release = release_frames
        self.max_pull = max_pull  # cm: the anchor is dragged along when the animated ankle gets farther
        self.anchor = np.zeros((batch, 2, 3))
        self.since = np.full((batch, 2), 10**6)  # frames since the last planted frame
        self.was = np.zeros((batch, 2), bool)

    def foot_positions(self, root: np.ndarray, rotations: np.ndarray) -> np.ndarray:
        """(B, 3), (B, J, 4) -> (B, 2 feet, 3) ankle world positions (joint_Root is identity)."""
        idx = [rep.HIPS] + [j for chain in self.chains for j in chain[:-1]]
        R = quat_to_matrix(rotations[:, idx])  # (B, 5, 3, 3): hips, upper/lower leg L, upper/lower leg R
        out = []
        for c, chain in enumerate(self.chains):
            Rc, p = R[:, 0], root
            for k, j in enumerate(chain):
                p = p + Rc @ self.offsets[j]
                if k < len(chain) - 1:
                    Rc = Rc @ R[:, 1 + 2 * c + k]
            out.append(p)
        return np.stack(out, axis=1)

    def __call__(self, root: np.ndarray, rotations: np.ndarray, contacts: np.ndarray) -> np.ndarray:
        """Returns the rotations with the IK applied (a new array); updates the lock state."""
        feet = self.foot_positions(root, rotations)
        start = contacts & ~self.was
        self.anchor = np.where(start[..., None], feet, self.anchor)
        gap = self.anchor - feet
        dist = np.linalg.norm(gap, axis=-1, keepdims=True)
        self.anchor = feet + gap * np.minimum(1.0, self.max_pull / np.maximum(dist, 1e-9))
        self.since = np.where(contacts, 0, self.since + 1)
        self.was = contacts.copy()
        fade = np.clip(self.since / (self.release + 1.0), 0.0, 1.0)[..., None]  # 0 planted .. 1 free
        target = self.anchor + (feet - self.anchor) * fade
        active = self.since <= self.release
        if not active.any():
            return rotations
        # both legs of every active session in one vectorised IK call
        rows, legs = np.nonzero(active)
        chains = np.asarray(self.chains)[legs]  # (K, 3) joint indices up/low/foot
        up, low, foot = chains[:, 0], chains[:, 1], chains[:, 2]
        gh = rotations[rows, rep.HIPS]
        hip = root[rows] + quat_apply(gh, self.offsets[up])
        r_up, r_low, r_foot = two_bone_ik(gh, rotations[rows, up], rotations[rows, low], rotations[rows, foot], hip,
                                          self.offsets[low], self.offsets[foot], target[rows, legs])
        out = rotations.copy()
        out[rows, up], out[rows, low], out[rows, foot] = r_up, r_low, r_foot
        return out
