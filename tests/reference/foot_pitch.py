"""The feet's pitch toward the input's (`feet_kernels.follow_pitch`) in numpy, on whole clips:
the reference the compiled stage is tested against."""

from __future__ import annotations

import numpy as np

from models.motion.feet_kernels import PITCH_HIGH, PITCH_LOW
from models.motion.rotations import quat_apply, quat_exp, quat_inv, quat_mul


def sole(offsets: np.ndarray, chain: np.ndarray) -> np.ndarray:
    """One leg's sole direction: its toe bone laid level in the rest pose (unit)."""
    v = offsets[chain[3]] * [1.0, 0.0, 1.0]
    return v / np.linalg.norm(v)


def sole_pitch(rotations: np.ndarray, hips: int, chain: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(F,) the elevation (radians) of one leg's sole, its chain (hip joint, knee, ankle, toe)."""
    return np.arcsin(np.clip(_sole(rotations, hips, chain, offsets)[:, 1], -1.0, 1.0))


def sole_heading(rotations: np.ndarray, hips: int, chain: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(F,) the heading (radians about up) of one leg's sole."""
    v = _sole(rotations, hips, chain, offsets)
    return np.arctan2(v[:, 0], v[:, 2])


def _foot(rotations: np.ndarray, hips: int, chain: np.ndarray) -> np.ndarray:
    g = rotations[:, hips]
    for j in chain[:3]:
        g = quat_mul(g, rotations[:, j])
    return g


def _sole(rotations: np.ndarray, hips: int, chain: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    v = quat_apply(_foot(rotations, hips, chain), np.broadcast_to(sole(offsets, chain), (len(rotations), 3)))
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def ankle_heights(rotations: np.ndarray, root: np.ndarray, hips: int, chain: np.ndarray, offsets: np.ndarray):
    """(F,) one leg's ankle height over the root's (F, 3) rig, its chain (hip joint, knee, ankle, toe)."""
    g, p = rotations[:, hips], np.zeros((len(rotations), 3))
    for parent, child in zip((None, *chain[:2]), chain[:3]):
        if parent is not None:
            g = quat_mul(g, rotations[:, parent])
        p = p + quat_apply(g, np.broadcast_to(offsets[child], p.shape))
    return root[:, 1] + p[:, 1]


def followed_pitch(
    rot_in: np.ndarray,
    rotations: np.ndarray,
    root: np.ndarray,
    floor: np.ndarray,
    hips: int,
    chains: np.ndarray,
    offsets: np.ndarray,
    share: float,
) -> np.ndarray:
    """(F, J, 4) `rotations` with each foot whose sole points lower than the input's raised about
    the level axis across it, up to `share` of the way to the input's elevation: all of it where
    the ankle is at most PITCH_LOW over its `floor` (F, 2) and the input's over its lower ankle,
    none from PITCH_HIGH."""
    out, low = rotations.copy(), lambda h: np.clip((PITCH_HIGH - h) / (PITCH_HIGH - PITCH_LOW), 0.0, 1.0)
    at_root, rot_in = np.zeros((len(rot_in), 3)), rot_in / np.linalg.norm(rot_in, axis=-1, keepdims=True)
    ankles_in = np.stack([ankle_heights(rot_in, at_root, hips, chain, offsets) for chain in chains], -1)
    for leg, chain in enumerate(chains):
        height = ankle_heights(rotations, root, hips, chain, offsets) - floor[:, leg]
        near = share * low(height) * low(ankles_in[:, leg] - ankles_in.min(-1))
        v = _sole(rotations, hips, chain, offsets)
        axis = np.stack([-v[:, 2], np.zeros(len(v)), v[:, 0]], -1)  # v x up
        axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
        turn = near * np.maximum(
            sole_pitch(rot_in, hips, chain, offsets) - sole_pitch(rotations, hips, chain, offsets), 0
        )
        shin = quat_mul(quat_mul(rotations[:, hips], rotations[:, chain[0]]), rotations[:, chain[1]])
        foot = quat_mul(shin, rotations[:, chain[2]])
        turned = quat_mul(quat_inv(shin), quat_mul(quat_exp(axis * turn[:, None]), foot))
        out[:, chain[2]] = np.where(turn[:, None] > 0.0, turned, rotations[:, chain[2]])  # else as it was
    return out


def pitched_and_planted(
    planter, rot_in: np.ndarray, root: np.ndarray, rotations: np.ndarray, hints, share: float, plant: bool
):
    """A whole clip's feet pitched (`followed_pitch`, over the planter's floors as they were the
    frame before), then planted when `plant`, frame by frame as the stream does: (root, rotations,
    planted legs)."""
    state, out_root, out_rot = planter.init_state(1), root.copy(), rotations.copy()
    contacts = np.zeros((len(root), 2), bool)
    for t in range(len(root)):
        started = bool(state["feet_started"][0])
        floor = state["feet_floor"][:, :, 0] if started else np.full((1, 2), planter.floors[0])
        one = (root[t : t + 1], floor, planter.hips, planter.chains, planter.offsets, share)
        out_rot[t] = followed_pitch(rot_in[t : t + 1], rotations[t : t + 1], *one)[0]
        if plant:
            r, q, c, state = planter(state, root[t : t + 1], out_rot[t : t + 1], hints=hints[t : t + 1])
            out_root[t], out_rot[t], contacts[t] = r[0], q[0], c[0]
    return out_root, out_rot, contacts
