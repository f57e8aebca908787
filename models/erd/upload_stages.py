"""The fitted stages of an uploaded Style-ERD style, from its one clip.

Until its job fits a branch, an upload streams the neutral reconstruction with one output prior
carrying what the network makes to the clip's frames. It must carry from the same content and
pace, so the source is pooled from the neutral TRAIN clips nearest the clip (`descriptor`;
`upload_sources.npz`, `python -m models.erd fit --stages upload_sources`). All joints but the Hips
are carried; the source's spread is floored (`SOURCE_FLOOR_DEG`), not the fast part's gains.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..motion.bn_skeleton import HIPS
from ..motion.rotation_ball import comparable
from ..motion.rotations import quat_angle, quat_inv, quat_log, quat_mean, quat_mul
from ..motion.skeleton import Motion, Skeleton
from ..motion.style_carry import StyleCarry, gaussian_map, pinned, tangent_stats
from ..stages import Pipeline
from .features import NB, ROOTVEL, ROT, YAWRATE
from .slow_carry import SlowPrior
from .twist_range import TwistRange

if TYPE_CHECKING:
    from .runtime import ERDModel
    from .uploads import ERDStyles

SOURCES_FILE = "upload_sources.npz"
FIELDS = ("mean", "cov", "frames", "descriptor")  # per neutral clip: its output Gaussian, size and what it does
PAIRS = 8  # neutral clips an upload's source is pooled from (chosen on validation, model card)
SOURCE_FLOOR_DEG = 10.0  # the spread the source is taken to have at least (chosen on validation)
SOURCE_FRAMES = 240  # of each neutral clip, as `rotation_prior.FIT_FRAMES`


@dataclass(frozen=True)
class Sources:
    """Per TRAIN neutral clip: the neutral reconstruction's Gaussian, frames and `descriptor`."""

    mean: np.ndarray
    cov: np.ndarray
    frames: np.ndarray
    descriptor: np.ndarray

    def save(self, path: Path) -> Path:
        np.savez(path, **{k: getattr(self, k) for k in FIELDS})
        return path

    @classmethod
    def load(cls, path: Path) -> Sources:
        with np.load(path) as z:
            return cls(*(z[k] for k in FIELDS))

    def nearest(self, x: np.ndarray, k: int = PAIRS) -> tuple[np.ndarray, np.ndarray]:
        """The output Gaussian over the `k` neutral clips doing most alike `x` (F, 216)."""
        scale = np.maximum(self.descriptor.std(0), 1e-6)
        near = np.argsort(np.linalg.norm((self.descriptor - descriptor(x)) / scale, axis=1))[:k]
        return pooled(self.mean[near], self.cov[near], self.frames[near])


def descriptor(x: np.ndarray) -> np.ndarray:
    """Mean and spread of a clip's facing-frame Hips speed (forward, sideways) and turning rate."""
    v = np.concatenate([x[:, ROOTVEL][:, [0, 2]], x[:, YAWRATE : YAWRATE + 1]], 1)
    return np.concatenate([v.mean(0), v.std(0)])


def pooled(means: np.ndarray, covs: np.ndarray, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One Gaussian per joint from clips' Gaussians: frame-weighted mean, covariance about it."""
    w = frames / frames.sum()
    signs = np.sign(np.sum(means * means[:1], axis=-1, keepdims=True))  # one hemisphere
    m = np.einsum("c,cjk->jk", w, means * np.where(signs == 0, 1.0, signs))
    m = m / np.linalg.norm(m, axis=-1, keepdims=True)
    d = quat_log(quat_mul(quat_inv(m)[None], means))  # (C, J, 3)
    cov = np.einsum("c,cjik->jik", w, covs + d[..., :, None] * d[..., None, :])
    return m, cov


def carry_to(
    source: tuple[np.ndarray, np.ndarray],
    target: np.ndarray,
    fixed: tuple[int, ...] = (),
    clamp_only: tuple[int, ...] = (),
    floor: float = 0.0,
) -> StyleCarry:
    """A one-style carry from a source Gaussian to real rotations, as `StyleCarry.fit` would give."""
    mean, cov, radius = tangent_stats(target)
    lin = gaussian_map(np.asarray(source[1], np.float64) + floor**2 * np.eye(3), cov)
    src_mean = np.array(source[0], np.float64)
    return pinned(src_mean[None], mean[None], lin[None], radius[None], fixed, clamp_only)


def clip_rotations(model: ERDStyles, clip: Motion) -> tuple[np.ndarray, np.ndarray]:
    """The clip's rotations (N, 22, 4) as the priors read real frames, and its features (N, 216)."""
    x, _ = model.maker.sequence(clip.translations[:, 1], clip.rotations)
    q = np.zeros((len(x), NB + 1, 4))
    q[..., 3] = 1.0
    q[:, 1:] = x[:, ROT].reshape(-1, NB, 4)
    return q / np.linalg.norm(q, axis=-1, keepdims=True), x


def nearest_style(style_means: np.ndarray, q: np.ndarray) -> int:
    """The trained style whose mean rotations (S, J, 4) lie nearest the clip's (sum of squared angles)."""
    angle = quat_angle(style_means, quat_mean(q, axis=0)[None])
    return int(np.argmin(np.sum(angle**2, axis=1)))


def fit_stages(
    built_in: Pipeline, skeleton: Skeleton, q: np.ndarray, source: tuple[np.ndarray, np.ndarray]
) -> dict[str, SlowPrior | TwistRange]:
    """An upload's output prior and twist range by stage name (module docstring)."""
    out: dict[str, SlowPrior | TwistRange] = {}
    stage = built_in.output_prior
    if isinstance(stage, SlowPrior):
        carry = carry_to(source, comparable(q), (0,), (HIPS,), np.radians(SOURCE_FLOOR_DEG))
        fast = carry_to(source, comparable(q), (0,), (HIPS,)).damping  # the fast part's gains, unfloored
        out["output_prior"] = SlowPrior(("",), carry, None, stage.hips, fast)
    if built_in.twist_range is not None:
        out["twist_range"] = TwistRange.fit(skeleton, [q], ("",))
    return out


def fit_sources(model: ERDModel) -> Sources:
    """`Sources`: each TRAIN neutral clip's first `SOURCE_FRAMES` through the neutral reconstruction."""
    from ..data import build_index, load_motions, select
    from ..eval.run import stylise
    from .dataset import DATASET, STYLES
    from .uploads import neutral_branch

    clips = sorted(select(build_index([DATASET]), split="train", style=STYLES[0]), key=lambda c: c.name)
    inputs = [m.slice(0, SOURCE_FRAMES) for m in load_motions(clips)]
    twin = model.network_only("reconstruction", neutral_branch(model, {}))
    outs = stylise(twin, inputs, [twin.styles().index("reconstruction")] * len(inputs))
    fitted = [tangent_stats(comparable(o.rotations)) for o in outs]
    return Sources(
        np.stack([f[0] for f in fitted]),
        np.stack([f[1] for f in fitted]),
        np.array([m.num_frames for m in inputs], np.float64),
        np.stack([descriptor(model.maker.sequence(m.translations[:, 1], m.rotations)[0]) for m in inputs]),
    )
