"""LTI's stages over a whole clip in numpy: the reference the compiled stream
(`models.lti.kernels.step`) is tested against, frame for frame."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from models.lti import raised_arm
from models.lti import representation as rep
from models.lti.kernels import SHARE_FLOOR, eased
from models.lti.model import RAISE_EASE_S, LTIStyleModel, ease_keep
from models.motion.bn_skeleton import HIPS
from models.motion.feet_kernels import PITCH_SHARE
from models.motion.hands import clip_sway, raise_share, wave_share
from models.motion.hinge import kernel_floor
from models.motion.hinge_kernels import floor_bends
from models.motion.rotations import quat_exp
from models.motion.style_carry import StyleCarry

from .foot_pitch import pitched_and_planted
from .hands import hand_offsets_of
from .rotation_ball import clamp_rotations


def shares(offsets: np.ndarray, swayed: np.ndarray) -> np.ndarray:
    """(B, 2) how far each arm is moved: its hand's raise share times one minus its wave share,
    from the input's `hand_offsets` (B, 2, 3) and sway (B, 2)."""
    return raise_share(np.asarray(offsets)[..., 1]) * (1.0 - wave_share(swayed))


def eased_shares(share: np.ndarray, keep: float) -> np.ndarray:
    """(F, 2) one session's `shares` eased frame by frame as the stream does
    (`kernels.raised_shares`), 0 below `SHARE_FLOOR`."""
    out = np.stack([eased(side, keep) for side in np.asarray(share, np.float64).T], axis=1)
    return np.where(out >= SHARE_FLOOR, out, 0.0)


def carried(carry: StyleCarry, rotations: np.ndarray, weights: np.ndarray, share: np.ndarray) -> np.ndarray:
    """(B, J, 4) `rotations` with each side's arm moved toward what `carry` makes of it (style
    weights (B, S)) by that side's `share` (B, 2): a normalised blend of the quaternions."""
    if not np.any(share > 0.0):
        return rotations
    out = np.array(rotations, np.float64)
    for side, joints in enumerate(raised_arm._ARM):
        rows = np.flatnonzero(share[:, side] > 0.0)
        if rows.size == 0:
            continue
        a = out[np.ix_(rows, joints)]
        b = carry(out[rows], weights[rows], hips=HIPS)[:, joints]
        b = np.where(np.sum(a * b, axis=-1, keepdims=True) < 0.0, -b, b)
        s = share[rows, side][:, None, None]
        mixed = (1.0 - s) * a + s * b
        out[np.ix_(rows, joints)] = mixed / np.linalg.norm(mixed, axis=-1, keepdims=True)
    return out


def features_to_sequence(
    features: np.ndarray, start_ground: np.ndarray, start_yaw: float, ref: np.ndarray = rep.IDENTITY_REF
) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of `sequence_features`: (F, 67) -> root (F, 3), rotations (F, 22, 4).

    The path is integrated from the given start: frame 0 sits at `start_ground`/`start_yaw`
    and frame t adds the displacement of frame t in the facing of frame t-1."""
    f = len(features)
    dyaw = features[:, 2].copy()
    dyaw[0] = 0.0
    yaw = start_yaw + np.cumsum(dyaw)
    step = np.zeros((f, 2))
    if f > 1:
        step[1:] = rep.rotate_y(features[1:, :2], yaw[:-1])
    ground = np.asarray(start_ground, float) + np.cumsum(step, axis=0)
    root = np.stack([ground[:, 0], features[:, 3], ground[:, 1]], axis=-1)
    return root, static_to_rotations(features[:, 4:], yaw, ref)


def static_to_rotations(static_rot: np.ndarray, yaw: np.ndarray, ref: np.ndarray = rep.IDENTITY_REF) -> np.ndarray:
    """(..., 63) tilt + body expmaps and yaw -> (..., 22, 4) local rotations."""
    lead = static_rot.shape[:-1]
    out = np.empty(lead + (rep.NUM_JOINTS, 4))
    out[..., 0, :] = (0.0, 0.0, 0.0, 1.0)
    out[..., 1:, :] = (rep._cached(ref)[0] @ quat_exp(static_rot.reshape(*lead, 21, 3))[..., None])[..., 0]
    c, s = np.cos(0.5 * yaw)[..., None], np.sin(0.5 * yaw)[..., None]
    t = out[..., rep.HIPS, :]
    # yaw_quat(yaw) * t, written out: (c*x + s*z, c*y + s*w, c*z - s*x, c*w - s*y)
    out[..., rep.HIPS, :] = c * t + s * t[..., [2, 3, 0, 1]] * np.array([1.0, 1.0, -1.0, -1.0])
    return out


def offline(model: LTIStyleModel, style: str, motion, footlock: bool = True):
    """A whole `Motion` (BN skeleton) translated toward `style` by `model`'s translator and the
    stages it has on, in numpy. Returns (Motion, contacts (F, 2))."""
    tr = model.translators[style]
    feats = rep.motion_to_features(motion, tr.ref)
    out, xs = tr.translate_features(feats, model.blend, model.saturate)
    yaw0, _ = rep.split_hips(motion.rotations[0, rep.HIPS])
    root, rots = features_to_sequence(
        out[:, : rep.FEATURE_DIM], motion.translations[0, rep.HIPS, [0, 2]], float(yaw0), tr.ref
    )
    if tr.prior_mean is not None and tr.prior_radii is not None:
        rots = clamp_rotations(rots, tr.prior_mean, tr.prior_radii)
    if model.hinges is not None:
        rots = floor_bends(rots, *kernel_floor(motion.skeleton, model.hinges))
    offsets = hand_offsets_of(motion.rotations, motion.skeleton)  # as the stream measures them
    swayed = clip_sway(offsets, motion.fps)
    if tr.raised_arm is not None:
        share = eased_shares(shares(offsets, swayed), ease_keep(LTIStyleModel.fps, RAISE_EASE_S))
        rots = carried(tr.raised_arm, rots, np.ones((len(rots), 1)), share)
    contacts = tr.footplant.predict(xs) if tr.footplant is not None else np.zeros((len(out), 2), bool)
    if model.foot_pitch:
        share = PITCH_SHARE
        planted = pitched_and_planted(model.planter, motion.rotations, root, rots, contacts, share, footlock)
        root, rots, contacts = planted if footlock else (root, planted[1], contacts)
    elif footlock:
        root, rots, contacts = model.planter.clip(root, rots, hints=contacts)
    translations = np.broadcast_to(motion.translations[:1], (len(root),) + motion.translations.shape[1:]).copy()
    translations[:, rep.HIPS] = root
    return replace(motion, rotations=rots, translations=translations), contacts
