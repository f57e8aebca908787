"""Another performer's bone twists onto the model's own: a reference-pose calibration in front
of every method, measured online per session.

Mocap solves and rigs disagree on how far each bone is turned about itself. Bandai Namco's two
recording sessions share one skeleton and a neutral walk looks alike in both, yet dataset 1's
upper arms sit about 42 degrees further twisted than dataset 2's (its elbows bend in another
plane of the arm's frame). No joint position shows a twist, so the retargeter cannot see it,
but a model fed rotations reads it as input it never saw: LTI's blend hands such frames back
unchanged, the networks style them as something else.

So, per session, this stage measures each bone's mean orientation relative to the hips over
the session's first `WINDOW_S` seconds, and turns the bone's frame about the bone by the twist
that brings that mean onto the model's reference (the mean over the neutral clips it was
trained on, `TwistReference.fit`), ramping in as the measurement fills. The model styles the
calibrated frame; its output is turned back by the same twists, so the client gets its own
rig's twists with the style on top. Twist only, as a production retargeter splits it off
(Unity's muscle space is relative to a reference pose, with the twist apart): a bone turned
about itself moves no joint, so what the body does is kept whatever the first seconds show,
and a difference in where a bone points is the performer's posture, which is left to the style.
The mean stops moving after the window, so later content (a crouch, a wave) is not taken for
the performer's rig.

`python -m models.motion.calibration fit --method NAME --datasets ... --styles normal` writes
`models/weights/calibration/<NAME>.npz`; `report` prints the twists measured on any clips.
"""

from __future__ import annotations

import argparse
import functools
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..interface import FrameBatch, State
from ..stages import put_in_front
from .bn_skeleton import BN_JOINTS, HIPS, PRIMARY_CHILD
from .calibration_kernels import APPLIED, PER_JOINT, calibrate_in, calibrate_out, state_width
from .rotations import quat_apply, quat_mean
from .skeleton import Skeleton

FOLDER = "calibration"  # under the weights folder: <method>.npz
WINDOW_S = 3.0  # seconds of each session's start whose mean rotations set its twists
RAMP_S = 1.0  # ... which then come in over this long
KEY = "calibration.state"  # (B, `state_width`) in the session state


def reference_path(weights_dir: Path, method: str) -> Path:
    return Path(weights_dir) / FOLDER / f"{method}.npz"


def bone_axes(skeleton: Skeleton) -> np.ndarray:
    """(J, 3) unit axis of each joint's bone in its own frame: toward its main child, or for a
    leaf (head, hand, toes) along its own offset, the bone it continues. Zero for the root and
    the hips, which carry the heading and are not turned."""
    axes = np.zeros((len(skeleton.names), 3))
    for j, name in enumerate(skeleton.names):
        if j <= HIPS:
            continue
        child = PRIMARY_CHILD.get(name)
        bone = skeleton.offsets[skeleton.names.index(child)] if child else skeleton.offsets[j]
        axes[j] = bone / np.linalg.norm(bone)
    return axes


@dataclass(frozen=True)
class TwistReference:
    """The model's own neutral clips, each as its mean local rotation per joint, the direction
    its bones point at that mean, and each bone's axis."""

    means: np.ndarray  # (K, J, 4)
    axes: np.ndarray  # (J, 3)
    parents: np.ndarray  # (J,)
    deadzone: np.ndarray  # (J,) radians of twist left alone: what the model's own held-out takes get

    @functools.cached_property
    def directions(self) -> np.ndarray:
        """(K, J, 3) each clip's mean bone directions in their parents' frames."""
        return np.ascontiguousarray(quat_apply(self.means, np.broadcast_to(self.axes, self.means.shape[:-1] + (3,))))

    @classmethod
    def fit(cls, train: list[np.ndarray], held_out: list[np.ndarray], skeleton: Skeleton, fps: float) -> TwistReference:
        """From clips' local rotations (F, J, 4) on the model rig: each TRAIN clip's mean, and per
        joint the largest twist a held-out clip of the same input gets (the model's own performer
        differs between takes by that much; only what lies beyond it is another rig's)."""
        means = np.stack([quat_mean(r / np.linalg.norm(r, axis=-1, keepdims=True), axis=0) for r in train])
        plain = cls(means, bone_axes(skeleton), np.asarray(skeleton.parents), np.zeros(len(skeleton.names)))
        return replace(plain, deadzone=np.max([plain.settled_twists(r, fps) for r in held_out], axis=0))

    def save(self, path: Path) -> Path:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(path, means=self.means.astype(np.float32), axes=self.axes, parents=self.parents, deadzone=self.deadzone)
        return path

    @classmethod
    def load(cls, path: Path) -> TwistReference:
        with np.load(path) as z:
            return cls(z["means"].astype(np.float64), z["axes"], z["parents"].astype(np.int64), z["deadzone"])

    def init_state(self, batch: int) -> np.ndarray:
        return np.zeros((batch, state_width(self.axes.shape[0])))

    def calibrate(self, rotations: np.ndarray, state: np.ndarray, fps: float) -> np.ndarray:
        """One frame of B sessions (B, J, 4) turned onto the reference's twists; advances state."""
        out = np.empty(rotations.shape)
        calibrate_in(
            rotations.astype(np.float64),
            self.parents,
            self.axes,
            self.deadzone,
            self.means,
            self.directions,
            WINDOW_S * fps,
            RAMP_S * fps,
            state,
            out,
        )
        return out

    def restore(self, rotations: np.ndarray, state: np.ndarray) -> np.ndarray:
        """A model's output frame (B, J, 4) turned back onto each session's own twists."""
        out = np.empty(rotations.shape)
        calibrate_out(rotations.astype(np.float64), self.parents, state, out)
        return out

    def clip(self, rotations: np.ndarray, fps: float) -> tuple[np.ndarray, np.ndarray]:
        """A whole clip (F, J, 4) through one session: its calibrated frames and the twists
        (F, J, 4) applied at each."""
        state = self.init_state(1)
        J = self.axes.shape[0]
        frames, twists = [], []
        for frame in rotations:
            frames.append(self.calibrate(frame[None], state, fps)[0])
            twists.append(state[0, : PER_JOINT * J].reshape(J, PER_JOINT)[:, APPLIED : APPLIED + 4].copy())
        return np.stack(frames), np.stack(twists)

    def settled_twists(self, rotations: np.ndarray, fps: float) -> np.ndarray:
        """(J,) radians each joint of a clip's session is turned once its twists are in."""
        last = self.clip(rotations[: int((WINDOW_S + RAMP_S) * fps) + 1], fps)[1][-1]
        w = np.where(np.abs(last).sum(-1) > 0, np.abs(last[:, 3]), 1.0)
        return 2 * np.arccos(np.clip(w, 0.0, 1.0))


class CalibratesTwist:
    """Put in front of a method's class (`with_calibration`): its sessions' input is turned onto
    the model's own bone twists and its output turned back."""

    calibration: TwistReference

    def init_state(self, batch: int, *args: Any, **kwargs: Any) -> State:
        inner = super().init_state(batch, *args, **kwargs)  # type: ignore[misc]
        return {**inner, KEY: self.calibration.init_state(batch)}

    def upgrade_state(self, state: State) -> State:
        inner = {k: v for k, v in state.items() if k != KEY}
        upgrade = getattr(super(), "upgrade_state", None)
        upgraded = inner if upgrade is None else upgrade(inner)
        own = state.get(KEY)
        if own is None or own.shape[1] != state_width(self.calibration.axes.shape[0]):
            own = self.calibration.init_state(len(next(iter(upgraded.values()))))  # a snapshot from before
        elif upgraded is inner:
            return state
        return {**upgraded, KEY: own}

    def step_batch(self, state: State, frames: FrameBatch, style_weights: np.ndarray) -> tuple[FrameBatch, State]:
        own = state[KEY].copy()
        fps = float(self.fps)  # type: ignore[attr-defined]
        turned = self.calibration.calibrate(frames.rotations, own, fps)
        calibrated = FrameBatch(frames.root, turned, frames.contacts, frames.control, frames.faded)
        out, new = super().step_batch(state, calibrated, style_weights)  # type: ignore[misc]
        restored = FrameBatch(out.root, self.calibration.restore(out.rotations, own), out.contacts, out.control, out.faded)
        return restored, {**new, KEY: own}


def with_calibration(model: Any, reference: TwistReference) -> Any:
    """`model` with the twist calibration in front of everything it does."""
    staged = put_in_front(model, CalibratesTwist)
    staged.calibration = reference
    return staged


def main(argv: list[str] | None = None) -> int:
    from .novelty import _as_model, _clips

    p = argparse.ArgumentParser(prog="python -m models.motion.calibration", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    for name in ("fit", "report"):
        s = sub.add_parser(name)
        s.add_argument("--method", required=True, help="the model whose reference is fitted or read (lti, erd, lpn)")
        s.add_argument("--datasets", required=True, help="comma-separated datasets")
        s.add_argument("--styles", help="comma-separated input styles (default: every one)")
    sub.choices["report"].add_argument("--split", default="val")
    args = p.parse_args(argv)
    from ..settings import get_settings
    from .assets import bandai_namco_skeleton

    styles = args.styles.split(",") if args.styles else None
    path = reference_path(get_settings().weights_dir, args.method)
    if args.cmd == "fit":
        train = [_as_model(m)[0] for m in _clips(args.datasets.split(","), None, styles, "train")[1]]
        held_out = [_as_model(m)[0] for m in _clips(args.datasets.split(","), None, styles, "val")[1]]
        ref = TwistReference.fit(train, held_out, bandai_namco_skeleton(), 30.0).save(path)
        print(f"{path}: {len(train)} train clips, dead zones (deg) {np.degrees(TwistReference.load(ref).deadzone).round(1)}")
        return 0
    ref = TwistReference.load(path)
    clips, motions = _clips(args.datasets.split(","), None, styles, args.split)
    for clip, m in zip(clips, motions):
        deg = np.degrees(ref.settled_twists(_as_model(m)[0], 30.0))
        top = np.argsort(deg)[::-1][:3]
        print(f"{clip.name:50s} " + "  ".join(f"{BN_JOINTS[j]} {deg[j]:5.1f}" for j in top))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
