"""Another performer's posture into the model's range: a calibration in front of a method,
measured online per session, and undone on its output.

Performers hold a body differently, which a model reads as unseen input on every frame. Each
joint's mean over a session's first `WINDOW_S` seconds, where outside the range of the model's own
neutral TRAIN clips' means (`PostureRange.fit`), is turned inside (ramped over `RAMP_S`), and the
output turned back. Legs and hinge joints are never turned; later frames do not change the turns.

`python -m models.motion.calibration fit --method NAME --datasets ... --styles normal` writes
`models/weights/calibration/<NAME>.npz`; `report` prints the turns measured on any clips.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..interface import FrameBatch, State
from ..stages import put_in_front, upgrade_with_own
from .bn_skeleton import BN_JOINTS
from .calibration_kernels import APPLIED, PER_JOINT, calibrate_in, calibrate_out, state_width
from .feet import LEG_JOINTS
from .hinge import fit_hinges
from .rotations import quat_inv, quat_log, quat_mean, quat_mul
from .skeleton import Skeleton

FOLDER = "calibration"  # under the weights folder: <method>.npz
WINDOW_S = 1.5  # seconds of each session's start whose mean rotations set its turns
RAMP_S = 0.5  # ... which then come in over this long
RANGE = (1.0, 99.0)  # percentiles of the model's clips' means that bound a session's mean
KEY = "calibration.state"  # (B, `state_width`) in the session state


def reference_path(weights_dir: Path, method: str) -> Path:
    return Path(weights_dir) / FOLDER / f"{method}.npz"


@dataclass(frozen=True)
class PostureRange:
    """Per joint, the model's own mean local rotation and the range of its clips' means about it."""

    reference: np.ndarray  # (J, 4)
    lo: np.ndarray  # (J, 3) rotation vector about the reference, radians
    hi: np.ndarray  # (J, 3)

    @classmethod
    def fit(cls, clips: list[np.ndarray], skeleton: Skeleton) -> PostureRange:
        """From clips' rotations: the mean of means and the `RANGE` percentiles of clip means about it."""
        means = np.stack([quat_mean(r / np.linalg.norm(r, axis=-1, keepdims=True), axis=0) for r in clips])
        reference = quat_mean(means, axis=0)
        about = quat_log(quat_mul(quat_inv(reference)[None], means))
        lo, hi = np.percentile(about, RANGE, axis=0)
        hinges = fit_hinges(skeleton, np.concatenate(clips)).joints
        held = sorted({BN_JOINTS.index(n) for n in LEG_JOINTS} | {int(j) for j in hinges})
        lo[held], hi[held] = -np.inf, np.inf
        return cls(reference, lo, hi)

    def save(self, path: Path) -> Path:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(path, reference=self.reference, lo=self.lo, hi=self.hi)
        return path

    @classmethod
    def load(cls, path: Path) -> PostureRange:
        with np.load(path) as z:
            return cls(z["reference"], z["lo"], z["hi"])

    def init_state(self, batch: int) -> np.ndarray:
        return np.zeros((batch, state_width(len(self.reference))))

    def calibrate(self, rotations: np.ndarray, state: np.ndarray, fps: float) -> np.ndarray:
        """One frame of B sessions (B, J, 4) turned into the model's range; advances state."""
        out = np.empty(rotations.shape)
        calibrate_in(
            rotations.astype(np.float64), self.reference, self.lo, self.hi, WINDOW_S * fps, RAMP_S * fps, state, out
        )
        return out

    def restore(self, rotations: np.ndarray, state: np.ndarray) -> np.ndarray:
        """A model's output frame (B, J, 4) turned back onto each session's own posture."""
        out = np.empty(rotations.shape)
        calibrate_out(rotations.astype(np.float64), state, out)
        return out

    def clip(self, rotations: np.ndarray, fps: float) -> tuple[np.ndarray, np.ndarray]:
        """A whole clip through one session: (calibrated frames, turns (F, J, 4))."""
        state = self.init_state(1)
        J = len(self.reference)
        frames, turns = [], []
        for frame in rotations:
            frames.append(self.calibrate(frame[None], state, fps)[0])
            turns.append(state[0, : PER_JOINT * J].reshape(J, PER_JOINT)[:, APPLIED : APPLIED + 4].copy())
        return np.stack(frames), np.stack(turns)

    def settled_turns(self, rotations: np.ndarray, fps: float) -> np.ndarray:
        """(J,) radians each joint of a clip's session is turned once its turns are in."""
        last = self.clip(rotations[: int((WINDOW_S + RAMP_S) * fps) + 1], fps)[1][-1]
        w = np.where(np.abs(last).sum(-1) > 0, np.abs(last[:, 3]), 1.0)
        return 2 * np.arccos(np.clip(w, 0.0, 1.0))


class CalibratesPosture:
    """Put in front of a method's class (`with_calibration`): input turned in, output turned back."""

    calibration: PostureRange

    def init_state(self, batch: int, *args: Any, **kwargs: Any) -> State:
        inner = super().init_state(batch, *args, **kwargs)  # type: ignore[misc]
        return {**inner, KEY: self.calibration.init_state(batch)}

    def upgrade_state(self, state: State) -> State:
        width = state_width(len(self.calibration.reference))
        upgrade = getattr(super(), "upgrade_state", None)
        return upgrade_with_own(state, KEY, width, self.calibration.init_state, upgrade)

    def step_batch(self, state: State, frames: FrameBatch, style_weights: np.ndarray) -> tuple[FrameBatch, State]:
        own = state[KEY].copy()
        fps = float(self.fps)  # type: ignore[attr-defined]
        turned = self.calibration.calibrate(frames.rotations, own, fps)
        calibrated = FrameBatch(frames.root, turned, frames.contacts, frames.control, frames.faded)
        out, new = super().step_batch(state, calibrated, style_weights)  # type: ignore[misc]
        restored = FrameBatch(
            out.root, self.calibration.restore(out.rotations, own), out.contacts, out.control, out.faded
        )
        return restored, {**new, KEY: own}


def with_calibration(model: Any, reference: PostureRange) -> Any:
    """`model` with the posture calibration in front of everything it does."""
    staged = put_in_front(model, CalibratesPosture)
    staged.calibration = reference
    return staged


def main(argv: list[str] | None = None) -> int:
    from ..settings import get_settings
    from .novelty import fit_or_report, on_model_rig, selected

    args = fit_or_report("python -m models.motion.calibration", __doc__, argv)
    path = reference_path(get_settings().weights_dir, args.method)
    if args.cmd == "fit":
        from .assets import bandai_namco_skeleton

        train = [on_model_rig(m)[0] for m in selected(args, "train")[1]]
        PostureRange.fit(train, bandai_namco_skeleton()).save(path)
        print(f"{path}: {len(train)} train clips")
        return 0
    ref = PostureRange.load(path)
    clips, motions = selected(args, args.split)
    for clip, m in zip(clips, motions):
        deg = np.degrees(ref.settled_turns(on_model_rig(m)[0], 30.0))
        top = np.argsort(deg)[::-1][:3]
        print(f"{clip.name:50s} " + "  ".join(f"{BN_JOINTS[j]} {deg[j]:5.1f}" for j in top))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
