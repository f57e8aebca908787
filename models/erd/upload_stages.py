"""The fitted stages of an uploaded Style-ERD style, from its one clip, the way `rotation_prior.py`
fits them for a trained style from its TRAIN clips.

Each stage maps a source distribution onto the style's real one (`models.motion.style_carry`).
For a trained style both come from data at fit time; for an upload the target is its clip and the
sources are what every trained style's fit started from, kept beside the weights as Gaussians
(`upload_sources.npz`, written by `python -m models.erd fit --stages upload_sources`):

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
from typing import TYPE_CHECKING

import numpy as np

from ..motion.bn_skeleton import HIPS
from ..motion.feet import LEG_JOINTS
from ..motion.rotation_ball import comparable
from ..motion.rotations import quat_mean
from ..motion.skeleton import Motion, Skeleton
from ..motion.style_carry import StyleCarry, gaussian_map, tangent_stats
from ..stages import Pipeline
from .features import NB, ROT
from .gait import clip_smoothed_speed, run_share
from .rotation_prior import FIXED
from .slow_carry import SlowPrior
from .twist_range import TwistRange

if TYPE_CHECKING:
    from .runtime import ERDModel
    from .uploads import ERDStyles

SOURCES_FILE = "upload_sources.npz"
KEYS = ("leaf_prior", "output_prior", "run_leaf_prior", "run_output_prior")  # the priors' sources, by name
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
    source: tuple[np.ndarray, np.ndarray],
    target: np.ndarray,
    fixed: tuple[int, ...] = (),
    clamp_only: tuple[int, ...] = (),
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


def clip_rotations(model: ERDStyles, clip: Motion) -> tuple[np.ndarray, np.ndarray]:
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
    built_in: Pipeline,
    sources: Sources,
    skeleton: Skeleton,
    q: np.ndarray,
    share: np.ndarray,
    nearest: int,
    output_source: tuple[np.ndarray, np.ndarray] | None = None,
) -> dict[str, SlowPrior | TwistRange]:
    """An upload's priors and twist range, by stage name, from its clip's rotations `q` and run
    shares (module docstring); `output_source` (mean, cov) replaces the nearest style's network
    source (a job that fitted the style's own branch measured its own). `built_in`: the trained
    styles' stages (one that is off stays off)."""
    legs = tuple(skeleton.index(n) for n in LEG_JOINTS)
    runs = q[share > 0.5]
    out: dict[str, SlowPrior | TwistRange] = {}
    for key, real, walk_src, fixed, clamped, run_clamped in (
        ("leaf_prior", q, sources.of("leaf_prior", nearest), FIXED, (), ()),
        ("output_prior", comparable(q), output_source, (0,), (HIPS,) + legs, (HIPS,)),
    ):
        stage = getattr(built_in, key)
        if not isinstance(stage, SlowPrior):
            continue
        walk = carry_to(walk_src or sources.of(key, nearest), real, fixed, clamped)
        run = None if stage.run is None else one_style(stage.run, nearest)
        if run is not None and len(runs) >= MIN_RUN_FRAMES:
            run_real = runs if key == "leaf_prior" else comparable(runs)
            run = carry_to(sources.of(f"run_{key}", nearest), run_real, fixed, run_clamped)
        out[key] = SlowPrior(("",), walk, run, stage.hips)
    if built_in.twist_range is not None:
        out["twist_range"] = TwistRange.fit(skeleton, [q], ("",))
    return out


def fit_sources(model: ERDModel) -> Sources:
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
