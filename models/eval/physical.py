"""What a viewer sees go wrong, measured so that no clamp or lock in a model enforces it.

- plausible clip: each body joint near some real frame of the style (not inside a ball about the
  mean, which the models' own balls pass by construction) in >= 95 % of frames;
- pops: the worst joint's share of frames past the p99.9 real rotation acceleration;
- jitter: the worst joint's p99 rotation acceleration over the larger of the input's and style's;
- slide: the worst content's p95 planted-foot speed over the larger of the real style's on that
  content and the input's own (a shuffling style drags its feet for real);
- path: the hips' path length over the input's, and how far apart the two paths end.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..motion.features import body_joint, left_leg_length
from ..motion.rotations import quat_inv, quat_log, quat_mean, quat_mul
from ..motion.skeleton import Motion
from .metrics import SKID_SPEED, flat_foot_contacts, planted, touchdown_speeds
from .plausibility import body_joints, comparable_rotations, rotation_acceleration

PLAUSIBLE_FRAMES = 0.95  # a joint is plausible in a clip when this share of its frames is
SUPPORT_FRAMES = 40_000  # real TRAIN frames per style in each joint's search tree (evenly spread)
REAL_CLIPS_PASSING = 0.95  # the share of held-out real clips the radius is calibrated to pass
# degrees, the least "near" means: an invisible half-degree off a real hinge must not fail a clip
MIN_RADIUS_DEG = 5.0
# leg lengths / s (2.6 cm/s on BN), the least slide allowed: real standing clips creep that much
SLIDE_FLOOR = 0.03


def _log_about(q: np.ndarray, mean: np.ndarray) -> np.ndarray:
    """(F, J, 3) rotation vectors from each joint's mean: fast for a KD-tree, ~angles near the data."""
    return quat_log(quat_mul(quat_inv(mean), q))


class RotationSupport:
    """Per style and joint: a search tree over real TRAIN rotations, with radii passing
    `REAL_CLIPS_PASSING` of held-out real clips (at least `MIN_RADIUS_DEG`): as close as real."""

    def __init__(self, train: dict[str, list[Motion]], held: dict[str, list[Motion]]):
        sk = next(iter(train.values()))[0].skeleton
        self.joint_index = body_joints(sk)
        self.joints = [sk.names[j] for j in self.joint_index]
        self.mean: dict[str, np.ndarray] = {}
        self.trees: dict[str, list[cKDTree]] = {}
        self.radius: dict[str, np.ndarray] = {}
        for style, motions in train.items():
            build = self._rotations(motions)
            build = build[np.linspace(0, len(build) - 1, min(len(build), SUPPORT_FRAMES)).astype(int)]
            self.mean[style] = quat_mean(build, axis=0)
            pts = _log_about(build, self.mean[style])
            self.trees[style] = [cKDTree(pts[:, j]) for j in range(len(self.joints))]
            clips = [self._distances(style, self._rotations([m])) for m in held[style]]
            base = np.percentile(np.concatenate(clips), 99, axis=0)
            worst = [float((np.percentile(d, 100 * PLAUSIBLE_FRAMES, axis=0) / base).max()) for d in clips]
            scaled = base * max(1.0, float(np.percentile(worst, 100 * REAL_CLIPS_PASSING)))
            self.radius[style] = np.maximum(scaled, np.radians(MIN_RADIUS_DEG))

    def _rotations(self, motions: list[Motion]) -> np.ndarray:
        return np.concatenate([comparable_rotations(m)[:, self.joint_index] for m in motions])

    def _distances(self, style: str, q: np.ndarray) -> np.ndarray:
        """(F, J) distance of each frame's joint rotation to the nearest real one."""
        x = _log_about(q, self.mean[style])
        return np.stack([tree.query(x[:, j])[0] for j, tree in enumerate(self.trees[style])], axis=1)

    def rotations(self, motion: Motion) -> np.ndarray:
        """(F, J, 4) the clip's rotations of the joints this support judges."""
        return comparable_rotations(motion)[:, self.joint_index]

    def within(self, style: str, motion: Motion, kept: np.ndarray | None = None) -> np.ndarray:
        """(J,) share of frames whose joint rotation is near a real one; with `kept` (the input's own
        rotations), near the input's counts too: a content the style never performed has no real frame."""
        q = self.rotations(motion)
        dist = self._distances(style, q)
        if kept is not None:
            n = min(len(q), len(kept))
            own = np.linalg.norm(quat_log(quat_mul(quat_inv(kept[:n]), q[:n])), axis=-1)
            dist[:n] = np.minimum(dist[:n], own)
        return (dist <= self.radius[style]).mean(axis=0)


@dataclass
class Reference:
    """What a row is measured against: rotation support, pop limit, p99 acceleration, slide p95."""

    support: RotationSupport
    pop_limit: np.ndarray  # (J,) degrees per frame per frame
    style_p99: dict[str, np.ndarray]  # style -> (J,)
    skate_limit: float  # units/s
    slide: dict[str, dict[str, float]]  # style -> content -> p95 planted-foot speed (TRAIN and VALIDATION), units/s
    slide_floor: float  # units/s

    @classmethod
    def fit(
        cls,
        train: dict[str, list[Motion]],
        real: dict[str, list[Motion]],
        train_contents: dict[str, list[str]],
        real_contents: dict[str, list[str]],
    ) -> Reference:
        """From TRAIN and VALIDATION clips per style; slides pool both (few takes per content)."""
        support = RotationSupport(train, real)
        acc = {s: np.concatenate([rotation_acceleration(m, support.joint_index) for m in ms]) for s, ms in real.items()}
        feet = {s: [planted_speeds(m) for m in ms] for s, ms in real.items()}
        slide = {
            s: _p95_by_content(feet[s] + [planted_speeds(m) for m in train[s]], real_contents[s] + train_contents[s])
            for s in real
        }
        return cls(
            support,
            np.percentile(np.concatenate(list(acc.values())), 99.9, axis=0),
            {s: np.percentile(a, 99, axis=0) for s, a in acc.items()},
            float(np.percentile(np.concatenate([f for fs in feet.values() for f in fs]), 95)),
            slide,
            SLIDE_FLOOR * left_leg_length(next(iter(real.values()))[0].skeleton),
        )


def _p95_by_content(speeds: list[np.ndarray], contents: list[str]) -> dict[str, float]:
    """Pooled p95 of clips' planted-foot speeds per content (contents with no planted frame left out)."""
    pooled = {c: np.concatenate([s for s, k in zip(speeds, contents) if k == c]) for c in set(contents)}
    return {c: float(np.percentile(v, 95)) for c, v in pooled.items() if len(v)}


def planted_speeds(motion: Motion) -> np.ndarray:
    """Horizontal speeds (units/s) of the feet over the frames each is planted flat."""
    return planted(*flat_foot_contacts(motion))


@dataclass
class ClipPhysics:
    """One output clip's measurements (against its input where a ratio needs one)."""

    within: np.ndarray  # (J,) share of frames near real rotations
    acc: np.ndarray  # (F - 2, J) rotation acceleration, degrees per frame per frame
    jitter: float
    foot_speeds: np.ndarray  # planted-foot speeds, units/s
    input_speeds: np.ndarray | None  # the input's planted-foot speeds, units/s
    landings: np.ndarray  # each touchdown's speed, leg lengths/s (`metrics.touchdown_speeds`)
    path_ratio: float
    end_drift: float  # units (cm on the model rig)

    @property
    def plausible(self) -> bool:
        return bool(self.within.min() >= PLAUSIBLE_FRAMES)


@dataclass
class Input:
    """An input clip's per-joint p99 rotation acceleration and hips path, measured once."""

    p99_acc: np.ndarray  # (J,) degrees per frame per frame
    hips_xz: np.ndarray  # (F, 2)
    leg: float  # units
    foot_speeds: np.ndarray  # planted-foot speeds, units/s
    rotations: np.ndarray  # (F, J, 4) the judged joints' rotations (`RotationSupport.rotations`)

    @classmethod
    def of(cls, motion: Motion, ref: Reference) -> Input:
        acc = rotation_acceleration(motion, ref.support.joint_index)
        leg = left_leg_length(motion.skeleton)
        rotations = ref.support.rotations(motion)
        return cls(np.percentile(acc, 99, axis=0), _hips_xz(motion), leg, planted_speeds(motion), rotations)


def measure(ref: Reference, style: str, out: Motion, inp: Input | None, content: str = "") -> ClipPhysics:
    """`content`: what the input performs (near the input's own rotations counts where the style lacks it)."""
    acc = rotation_acceleration(out, ref.support.joint_index)
    pos = out.global_positions()
    contacts, foot_speeds = flat_foot_contacts(out, pos)
    jitter, path_ratio, drift = float("nan"), float("nan"), float("nan")
    if inp is not None and out.num_frames > 3:
        jitter = float((np.percentile(acc, 99, axis=0) / np.maximum(inp.p99_acc, ref.style_p99[style])).max())
        path_ratio, drift = _paths(inp, _hips_xz(out, pos))
    speeds = None if inp is None else inp.foot_speeds
    kept = inp.rotations if inp is not None and content not in ref.slide.get(style, {}) else None
    return ClipPhysics(
        ref.support.within(style, out, kept),
        acc,
        jitter,
        planted(contacts, foot_speeds),
        speeds,
        touchdown_speeds(contacts, foot_speeds) / left_leg_length(out.skeleton),
        path_ratio,
        drift,
    )


def _hips_xz(motion: Motion, positions: np.ndarray | None = None) -> np.ndarray:
    pos = motion.global_positions() if positions is None else positions
    return pos[:, body_joint(motion.skeleton, "hips")][:, [0, 2]]


def _paths(inp: Input, b: np.ndarray) -> tuple[float, float]:
    a = inp.hips_xz
    length = lambda p: float(np.linalg.norm(np.diff(p, axis=0), axis=-1).sum())  # noqa: E731
    n = min(len(a), len(b))
    drift = float(np.linalg.norm((a[n - 1] - a[0]) - (b[n - 1] - b[0])))
    return (length(b) + inp.leg) / (length(a) + inp.leg), drift


def worst_slide(clips: list[ClipPhysics], contents: list[str], style: str, ref: Reference) -> tuple[float, str]:
    """(largest per-content slide ratio, its content): pooled planted-foot p95 over the largest of
    the real style's, the input's and SLIDE_FLOOR; a content the style never performs: the input's."""
    out = _p95_by_content([c.foot_speeds for c in clips], contents)
    given = [c.input_speeds for c in clips if c.input_speeds is not None]
    inputs = _p95_by_content(given, contents) if len(given) == len(clips) else {}  # none for real clips
    worst, where = 0.0, ""
    for content in sorted(out):
        limit = max(ref.slide_floor, ref.slide[style].get(content, 0.0), inputs.get(content, 0.0))
        if (ratio := out[content] / limit) > worst:
            worst, where = ratio, content
    return worst, where


def summarise(clips: list[ClipPhysics], ref: Reference, contents: list[str], style: str) -> dict:
    """A row's physical columns over its clips (`contents`: what each clip performs)."""
    joints = ref.support.joints
    acc = np.concatenate([c.acc for c in clips if len(c.acc)])
    pops = (acc > ref.pop_limit).mean(axis=0) if len(acc) else np.zeros(len(joints))
    feet = np.concatenate([c.foot_speeds for c in clips])
    landings = np.concatenate([c.landings for c in clips])
    finite = lambda xs: [x for x in xs if np.isfinite(x)]  # noqa: E731
    jit, ratio, drift = (finite([getattr(c, k) for c in clips]) for k in ("jitter", "path_ratio", "end_drift"))
    worst = min(clips, key=lambda c: c.within.min())
    slide_ratio, slide_content = worst_slide(clips, contents, style, ref)
    return {
        "plausible_hits": sum(c.plausible for c in clips),
        "worst_within": float(worst.within.min()),
        "worst_joint": joints[int(np.argmin(worst.within))],
        "pops": float(pops.max()),
        "pops_joint": joints[int(np.argmax(pops))],
        "jitter_median": float(np.median(jit)) if jit else float("nan"),
        "jitter_p90": float(np.percentile(jit, 90)) if jit else float("nan"),
        "slide_p95": float(np.percentile(feet, 95)) if len(feet) else 0.0,
        "slide_ratio": slide_ratio,
        "slide_content": slide_content,
        "skate": float((feet > ref.skate_limit).mean()) if len(feet) else 0.0,
        "skid": float((landings > SKID_SPEED).mean()) if len(landings) else 0.0,
        "path_ratio_median": float(np.median(ratio)) if ratio else float("nan"),
        "path_ratio_worst": float(max(ratio, key=lambda r: abs(np.log(r)))) if ratio else float("nan"),
        "end_drift_median": float(np.median(drift)) if drift else float("nan"),
    }
