"""Running sessions: a scored clip streamed after other motion, as in a live session, where slow
modes, hidden states and phases carry what came before. `with_history` precedes a clip by the
clips before it (cyclic), each continuing where the last ended through a short eased transition.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..motion.features import body_joint, facing_yaw
from ..motion.rotations import quat_mul, yaw_quat
from ..motion.skeleton import Motion

TRANSITION_FRAMES = 10  # a third of a second at 30 fps between one clip's last pose and the next's first


def _hips(motion: Motion) -> int:
    return body_joint(motion.skeleton, "hips")


def heading(motion: Motion, frame: int) -> float:
    """Which way the body faces at `frame` (radians about +Y, 0 = +Z), from hips and shoulders."""
    return float(facing_yaw(motion.slice(frame, frame + 1).global_positions()[0], motion.skeleton))


def placed(motion: Motion, ground: np.ndarray, yaw: float) -> Motion:
    """`motion` turned about +Y and moved so its first frame stands at `ground` facing `yaw`."""
    hips = _hips(motion)
    turn = yaw - heading(motion, 0)
    c, s = np.cos(turn), np.sin(turn)
    trans = motion.translations.copy()
    offset = trans[:, hips, [0, 2]] - trans[0, hips, [0, 2]]
    trans[:, hips, 0] = ground[0] + c * offset[:, 0] + s * offset[:, 1]
    trans[:, hips, 2] = ground[1] - s * offset[:, 0] + c * offset[:, 1]
    rots = motion.rotations.copy()
    rots[:, hips] = quat_mul(yaw_quat(np.full(len(rots), turn)), rots[:, hips])
    return replace(motion, rotations=rots, translations=trans)


def transition(a: Motion, b: Motion, frames: int = TRANSITION_FRAMES) -> Motion:
    """`frames` frames easing from `a`'s last pose to `b`'s first (nlerp, smoothstep), both excluded."""
    t = np.arange(1, frames + 1) / (frames + 1)
    w = (t * t * (3.0 - 2.0 * t))[:, None, None]
    q0, q1 = a.rotations[-1], b.rotations[0]
    q1 = np.where(np.sum(q0 * q1, axis=-1, keepdims=True) < 0, -q1, q1)
    rots = (1.0 - w) * q0 + w * q1
    rots /= np.linalg.norm(rots, axis=-1, keepdims=True)
    trans = (1.0 - w) * a.translations[-1] + w * b.translations[0]
    return replace(a, rotations=rots, translations=trans)


def continued(a: Motion, b: Motion, frames: int = TRANSITION_FRAMES) -> tuple[Motion, Motion]:
    """(the transition, `b` placed to continue `a`): `b` starts where `a` ends, facing the same way."""
    nxt = placed(b, a.translations[-1, _hips(a), [0, 2]], heading(a, a.num_frames - 1))
    return transition(a, nxt, frames), nxt


def with_history(clips: list[Motion], i: int, frames: int) -> tuple[Motion, int]:
    """Clip `i` after `frames` frames of the clips before it (cyclic): (motion, clip `i`'s first frame)."""
    before: list[Motion] = []
    total, k = 0, i
    while total < frames:
        k = (k - 1) % len(clips)  # with one clip, itself again
        before.insert(0, clips[k])
        total += clips[k].num_frames + TRANSITION_FRAMES
    parts = [before[0]]
    for nxt in before[1:] + [clips[i]]:
        bridge, moved = continued(parts[-1], nxt)
        parts += [bridge, moved]
    whole = replace(
        clips[i],
        rotations=np.concatenate([p.rotations for p in parts]),
        translations=np.concatenate([p.translations for p in parts]),
    )
    return whole, whole.num_frames - clips[i].num_frames
