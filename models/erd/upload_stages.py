"""The fitted stages of an uploaded Style-ERD style, from its one clip, the way `rotation_prior.py`
fits them for a trained style from its TRAIN clips.

Each stage maps a source distribution onto the style's real one (`models.motion.style_carry`).
For a trained style both come from data at fit time; for an upload the target is its clip and the
sources are what every trained style's fit started from, kept beside the weights as Gaussians
(`upload_sources.npz`, written by `python -m models.erd.rotation_prior sources`):

- leaf prior: real TRAIN `normal` frames -> the clip's frames;
- output prior: what the network makes of TRAIN neutral clips toward the style -> the clip's
  frames, the legs and Hips only clamped (an upload streams through its nearest trained style's
  branch until its job has fitted one of its own, so the source is that style's);
- run priors: the same on the clip's running frames (`gait.py`'s speed ramp) where it has enough
  of them; one clip seldom both walks and runs, so otherwise the nearest trained style's;
- twist range: the clip's p1-p99 arm twists (`twist_range.py`).

Which trained style is nearest is measured on the clip: the smallest sum over joints of squared
angles between the clip's mean local rotations and each trained style's real ones (the leaf
prior's style means).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..motion.bn_skeleton import HIPS
from ..motion.feet import LEG_JOINTS
from ..motion.rotation_ball import comparable
from ..motion.rotations import quat_mean
from ..motion.style_carry import StyleCarry, gaussian_map, tangent_stats
from .features import NB, ROT
from .gait import clip_smoothed_speed, run_share
from .rotation_prior import FIXED, PRIOR_FILES
from .stages import ErdStages
from .twist_range import TwistRange

SOURCES_FILE = "upload_sources.npz"
KEYS = tuple(PRIOR_FILES)  # the priors an upload fits
MIN_RUN_FRAMES = 60  # running frames a clip needs to fit its own run priors (2 s)


@dataclass(frozen=True)
class Sources:
    """Per prior: the Gaussian its fits carry from, mean (S or 1, J, 4) and covariance (S or 1, J, 3, 3)
    of tangent deviations; the leaf priors' (real neutral) are the same for every style."""

    mean: dict[str, np.ndarray]
    cov: dict[str, np.ndarray]

    def save(self, path: Path) -> Path:
        arrays = {f"{k}.mean": v for k, v in self.mean.items()} | {f"{k}.cov": v for k, v in self.cov.items()}
        np.savez(path, **arrays)  # type: ignore[arg-type]
        return path

    @classmethod
    def load(cls, path: Path) -> Sources:
        with np.load(path) as z:
            return cls({k: z[f"{k}.mean"] for k in KEYS}, {k: z[f"{k}.cov"] for k in KEYS})

    def of(self, key: str, style: int) -> tuple[np.ndarray, np.ndarray]:
        """The source Gaussian of prior `key` for trained style `style`."""
        mean, cov = self.mean[key], self.cov[key]
        i = 0 if len(mean) == 1 else style
        return mean[i], cov[i]


def carry_to(
    source: tuple[np.ndarray, np.ndarray], target: np.ndarray, fixed: tuple[int, ...] = (), clamp_only=()
) -> StyleCarry:
    """A one-style carry from a source Gaussian (mean (J, 4), cov (J, 3, 3)) to real rotations
    (N, J, 4): what `StyleCarry.fit` gives from the frames the source was measured on."""
    mean, cov, radius = tangent_stats(target)
    src_mean = np.array(source[0], np.float64)
    lin = gaussian_map(np.asarray(source[1], np.float64), cov)
    clamp_, fixed_ = list(clamp_only), list(fixed)
    src_mean[clamp_] = mean[clamp_]
    lin[clamp_] = np.eye(3)
    src_mean[fixed_] = mean[fixed_] = (0.0, 0.0, 0.0, 1.0)
    lin[fixed_] = np.eye(3)
    radius[fixed_] = np.pi
    return StyleCarry(*(np.ascontiguousarray(a[None]) for a in (src_mean, mean, lin, radius)))


def one_style(carry: StyleCarry, style: int) -> StyleCarry:
    return StyleCarry(*(np.ascontiguousarray(a[style : style + 1]) for a in carry.arrays))


def clip_rotations(model, clip) -> tuple[np.ndarray, np.ndarray]:
    """The clip's local rotations (N, 22, 4) as the priors read real frames (the feature cache's:
    Hips without the facing yaw, joint_Root the identity), and each frame's run share (N,)."""
    root = clip.translations[:, 1]
    x, _ = model.maker.sequence(root, clip.rotations)
    q = np.zeros((len(x), NB + 1, 4))
    q[..., 3] = 1.0
    q[:, 1:] = x[:, ROT].reshape(-1, NB, 4)
    share = run_share(clip_smoothed_speed(model.maker.positions(root, clip.rotations), model.fps))
    return q / np.linalg.norm(q, axis=-1, keepdims=True), share


def nearest_style(style_means: np.ndarray, q: np.ndarray) -> int:
    """The trained style whose real mean rotations (S, J, 4) lie nearest the clip's (`q` (N, J, 4))."""
    m = quat_mean(q, axis=0)
    angle = 2.0 * np.arccos(np.clip(np.abs(np.sum(style_means * m[None], axis=-1)), 0.0, 1.0))
    return int(np.argmin(np.sum(angle**2, axis=1)))


def fit_stages(
    built_in: ErdStages, sources: Sources, skeleton, q: np.ndarray, share: np.ndarray, nearest: int, output_source=None
) -> ErdStages:
    """An upload's priors and twist range from its clip's rotations `q` and run shares (module
    docstring); `output_source` (mean, cov) replaces the nearest style's network source (a job
    that fitted the style's own branch measured its own). `built_in`: the trained styles' stages
    (a missing one stays missing)."""
    legs = tuple(skeleton.index(n) for n in LEG_JOINTS)
    runs = q[share > 0.5]
    out: dict[str, Any] = {}  # the fitted priors, by field
    if built_in.leaf_prior is not None:
        out["leaf_prior"] = carry_to(sources.of("leaf_prior", nearest), q, FIXED)
    if built_in.output_prior is not None:
        src = output_source or sources.of("output_prior", nearest)
        out["output_prior"] = carry_to(src, comparable(q), (0,), (HIPS,) + legs)
    for key, real, clamped in (("run_leaf_prior", runs, None), ("run_output_prior", comparable(runs), (HIPS,))):
        carry = getattr(built_in, key)
        if carry is None:
            continue
        if len(runs) >= MIN_RUN_FRAMES:
            out[key] = carry_to(sources.of(key, nearest), real, FIXED if clamped is None else (0,), clamped or ())
        else:
            out[key] = one_style(carry, nearest)
    twists = None if built_in.twist_range is None else TwistRange.fit(skeleton, [q])
    return ErdStages(twist_range=twists, **out)


def fit_sources(model) -> Sources:
    """The sources every trained style's priors were fitted from (`rotation_prior.py`), as Gaussians."""
    from .rotation_prior import _neutral_inputs, network_rotations, real_rotations, run_network_rotations

    def stats(qs: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        fitted = [tangent_stats(q) for q in qs]
        return np.stack([f[0] for f in fitted]), np.stack([f[1] for f in fitted])

    mean, cov = {}, {}
    mean["leaf_prior"], cov["leaf_prior"] = stats([real_rotations()[0]])
    mean["run_leaf_prior"], cov["run_leaf_prior"] = stats([real_rotations(runs=True)[0]])
    mean["output_prior"], cov["output_prior"] = stats(network_rotations(model, _neutral_inputs()))
    mean["run_output_prior"], cov["run_output_prior"] = stats(run_network_rotations(model))
    return Sources(mean, cov)
