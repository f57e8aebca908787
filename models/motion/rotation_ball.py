"""Rotation ball: each joint's output rotation stays inside the ball real data of the style fills
around its mean (a skinned character shows the rotation itself).

The angle d to the mean is kept up to `inner`, then saturates smoothly toward `outer`:
    d' = inner + (outer - inner) tanh((d - inner) / (outer - inner))   for d > inner
(C1, so a crossing does not kink). The Hips is compared without its heading. Radii are quantiles
of real angles (`fit_prior`); compiled per frame in `rotation_ball_kernels.py`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..interface import State
from ..stages import Rows, StageFrame, Stateless, style_rows
from .bn_skeleton import HIPS
from .rotation_ball_kernels import clamp_mixed
from .rotations import quat_angle, quat_inv, quat_mul
from .skeleton import Skeleton

NO_PRIOR = np.inf  # radius of a joint (or a style) without a prior: nothing is clamped


def up_twist(q: np.ndarray) -> np.ndarray:
    """(..., 4) -> q's twist about +Y, normalised; identity when q has none (a horizontal half turn)."""
    t = np.zeros_like(q)
    t[..., 1], t[..., 3] = q[..., 1], q[..., 3]
    n = np.linalg.norm(t, axis=-1, keepdims=True)
    return np.where(n > 1e-12, t / np.maximum(n, 1e-300), np.array([0.0, 0.0, 0.0, 1.0]))


def split_heading(rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(heading (..., 4), rotations without it): priors compare without heading, never a style."""
    out = np.array(rotations, float, copy=True)
    out /= np.linalg.norm(out, axis=-1, keepdims=True)
    h = out[..., HIPS, :]
    heading = up_twist(h)
    out[..., HIPS, :] = quat_mul(quat_inv(heading), h)
    return heading, out


def comparable(rotations: np.ndarray) -> np.ndarray:
    """(..., J, 4) local rotations -> the same with the Hips' twist about up removed (`split_heading`)."""
    return split_heading(rotations)[1]


def mean_rotation(q: np.ndarray) -> np.ndarray:
    """(N, 4) -> (4,) sign-blind mean (principal eigenvector of sum q q^T), w >= 0."""
    _, vecs = np.linalg.eigh(q.T @ q)
    m = vecs[:, -1]
    return m if m[3] >= 0 else -m


def fit_prior(
    rotations: np.ndarray, inner_q: float = 97.0, outer_q: float = 99.0, margin_deg: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """Real frames (F, J, 4) -> (mean (J, 4), radii (2, J) inner, outer; radians); none for joint 0."""
    c = comparable(rotations)
    joints = c.shape[-2]
    mean = np.tile(np.array([0.0, 0.0, 0.0, 1.0]), (joints, 1))
    radii = np.full((2, joints), NO_PRIOR)
    for j in range(1, joints):
        mean[j] = mean_rotation(c[:, j])
        d = quat_angle(c[:, j], mean[j])
        outer = max(np.percentile(d, outer_q) - np.radians(margin_deg), 1e-3)
        radii[:, j] = min(np.percentile(d, inner_q), outer), outer
    return mean, radii


@dataclass(frozen=True)
class StyleBalls(Stateless):
    """One ball per style: `mean` (S, J, 4), `radii` (S, 2, J), and how they were fitted (`fit`)."""

    styles: tuple[str, ...]
    mean: np.ndarray
    radii: np.ndarray
    fit: dict = field(default_factory=dict)

    @classmethod
    def fit_styles(
        cls, rotations: dict[str, np.ndarray], inner_q: float, outer_q: float, margin_deg: float, data: str = ""
    ) -> StyleBalls:
        """Per style, real frames (F, J, 4) -> its ball (`fit_prior`)."""
        fitted = [fit_prior(q, inner_q, outer_q, margin_deg) for q in rotations.values()]
        return cls(
            tuple(rotations),
            np.stack([m for m, _ in fitted]),
            np.stack([r for _, r in fitted]),
            {"inner_q": inner_q, "outer_q": outer_q, "margin_deg": margin_deg, "data": data},
        )

    def rows(self, styles: Sequence[str | None], skeleton: Skeleton) -> dict[str, np.ndarray]:
        """`mean` and `radii` aligned with `styles`; a style without a ball: infinite radii."""
        J = skeleton.num_joints
        plain = (np.tile((0.0, 0.0, 0.0, 1.0), (J, 1)), np.full((2, J), NO_PRIOR))
        return style_rows(self.styles, styles, mean=(self.mean, plain[0]), radii=(self.radii, plain[1]))

    def step_batch(self, state: State, frame: StageFrame, rows: Rows) -> tuple[np.ndarray, State]:
        """The rotations held inside the balls of the frame's styles (`clamp_mixed`)."""
        rotations = frame.rotations
        out = np.empty(rotations.shape, np.float64)
        weights = np.ascontiguousarray(frame.weights, np.float64)
        clamp_mixed(np.ascontiguousarray(rotations, np.float64), weights, frame.base, rows["mean"], rows["radii"], out)
        return out.astype(rotations.dtype), state

    def with_styles_of(self, other: StyleBalls) -> StyleBalls:
        keep = [k for k, s in enumerate(self.styles) if s not in other.styles]
        mean, radii = (np.concatenate([a[keep], b]) for a, b in ((self.mean, other.mean), (self.radii, other.radii)))
        return StyleBalls(tuple(self.styles[k] for k in keep) + other.styles, mean, radii, other.fit)

    def save(self, path: Path) -> Path:
        import json

        np.savez_compressed(
            path,
            styles=np.array(self.styles),
            mean=self.mean.astype(np.float64),
            radii=self.radii.astype(np.float64),
            fit=np.array(json.dumps(self.fit)),
        )
        return path

    @classmethod
    def load(cls, path: Path) -> StyleBalls:
        import json

        with np.load(path) as z:
            return cls(tuple(str(s) for s in z["styles"]), z["mean"], z["radii"], json.loads(str(z["fit"])))
