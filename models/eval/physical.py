"""What a viewer sees go wrong, measured so that no clamp or lock in a model enforces it.

- **plausible clip**: every body joint's local rotation lies within the p99 distance of real
  VALIDATION clips of the style in ≥ 95 % of the clip's frames (the models' clamps stop at TRAIN
  statistics, and a clip fails on its worst joint, not on a pool over clips);
- **pops**: the worst joint's share of frames whose rotation acceleration passes the real p99.9,
  beside the same share of real clips of the style;
- **jitter**: each clip's p99 rotation acceleration over its input's, per joint, the worst joint
  (1 = no jitter added; a joint the input holds still counts from `STILL` degrees/frame², and
  per joint, because the planted feet's accelerations dominate a pool over joints);
- **slide**: the p95 horizontal speed of a planted foot (ankle and toe both on the floor,
  `metrics.flat_foot_contacts`; the median a foot lock pins to 0 says nothing), and the
  **skating** share: planted-foot frames faster than `skate_limit`, calibrated on real clips as
  their p95 (real clips skate in 5 % of planted frames by construction);
- **path**: the hips' path length over the input's, and how far apart the two paths end.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..motion.features import body_joint
from ..motion.skeleton import Motion
from .metrics import flat_foot_contacts
from .plausibility import RotationReference, rotation_acceleration

PLAUSIBLE_FRAMES = 0.95  # a joint is plausible in a clip when this share of its frames is
STILL = 1.0  # degrees per frame per frame: the p99 acceleration below which an input joint is still


def planted_speeds(motion: Motion) -> np.ndarray:
    """Horizontal speeds (units/s) of the feet over the frames each is planted flat."""
    contacts, speeds = flat_foot_contacts(motion)
    return speeds[1:][contacts[1:]]


def skate_limit(real: list[Motion]) -> float:
    """Planted-foot speed (units/s) that real clips pass in 5 % of their planted frames."""
    return float(np.percentile(np.concatenate([planted_speeds(m) for m in real]), 95))


@dataclass
class ClipPhysics:
    """One output clip's measurements (the input's where a ratio needs it)."""

    plausible: bool
    worst_within: float
    worst_joint: str
    acc: np.ndarray  # (F - 2, J) rotation acceleration, degrees per frame per frame
    jitter: float  # p99 acceleration, output / input
    foot_speeds: np.ndarray  # planted-foot speeds, units/s
    path_ratio: float
    end_drift: float  # units (cm on the model rig)


def measure(ref: RotationReference, style: str, out: Motion, inp: Motion | None) -> ClipPhysics:
    plaus = ref.plausibility(style, [out])
    acc = rotation_acceleration(out, ref.joint_index)
    jitter, path_ratio, drift = float("nan"), float("nan"), float("nan")
    if inp is not None and out.num_frames > 3:
        acc_in = rotation_acceleration(inp, ref.joint_index)
        p99_in = np.maximum(np.percentile(acc_in, 99, axis=0), STILL)
        jitter = float((np.percentile(acc, 99, axis=0) / p99_in).max())
        path_ratio, drift = _paths(inp, out)
    return ClipPhysics(
        plaus["min_within"] >= PLAUSIBLE_FRAMES,
        plaus["min_within"],
        plaus["worst_joint"],
        acc,
        jitter,
        planted_speeds(out),
        path_ratio,
        drift,
    )


def _paths(inp: Motion, out: Motion) -> tuple[float, float]:
    hips = body_joint(inp.skeleton, "hips")
    a = inp.global_positions()[:, hips][:, [0, 2]]
    b = out.global_positions()[:, hips][:, [0, 2]]
    length = lambda p: float(np.linalg.norm(np.diff(p, axis=0), axis=-1).sum())  # noqa: E731
    n = min(len(a), len(b))
    drift = float(np.linalg.norm((a[n - 1] - a[0]) - (b[n - 1] - b[0])))
    return length(b) / max(length(a), 1.0), drift


def summarise(clips: list[ClipPhysics], ref: RotationReference, style: str, limit: float) -> dict:
    """A row's physical columns over its clips."""
    acc = np.concatenate([c.acc for c in clips if len(c.acc)])
    pops = (acc > ref.pop_limit[style]).mean(axis=0) if len(acc) else np.zeros(len(ref.joints))
    feet = np.concatenate([c.foot_speeds for c in clips])
    finite = lambda xs: [x for x in xs if np.isfinite(x)]  # noqa: E731
    jit, ratio = finite([c.jitter for c in clips]), finite([c.path_ratio for c in clips])
    drift = finite([c.end_drift for c in clips])
    worst = min(clips, key=lambda c: c.worst_within)
    return {
        "plausible_hits": sum(c.plausible for c in clips),
        "worst_within": worst.worst_within,
        "worst_joint": worst.worst_joint,
        "pops": float(pops.max()),
        "pops_joint": ref.joints[int(np.argmax(pops))],
        "jitter_median": float(np.median(jit)) if jit else float("nan"),
        "jitter_p90": float(np.percentile(jit, 90)) if jit else float("nan"),
        "slide_p95": float(np.percentile(feet, 95)) if len(feet) else 0.0,
        "skate": float((feet > limit).mean()) if len(feet) else 0.0,
        "path_ratio_median": float(np.median(ratio)) if ratio else float("nan"),
        "path_ratio_worst": float(max(ratio, key=lambda r: abs(np.log(max(r, 1e-6))))) if ratio else float("nan"),
        "end_drift_median": float(np.median(drift)) if drift else float("nan"),
    }
