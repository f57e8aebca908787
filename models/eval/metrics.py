"""Foot-contact metrics on motions: flat-foot contacts and skating. Recognition
accuracies live in `judges.Judges`."""

from __future__ import annotations

import numpy as np

from ..motion.features import body_joint, left_leg_length
from ..motion.skeleton import Motion

SKATE_SPEED = 0.2  # leg lengths per second of horizontal foot motion while in contact counts as skating
CONTACT_MARGIN = 0.02  # leg lengths (1.7 cm on Bandai Namco) above a joint's floor level still counts as on the floor
FLOOR_PERCENTILE = 5.0  # a joint's floor level: this percentile of its height over the clip
# a foot must stay flat this long to count as planted: the swing foot passes as low for a frame or two
MIN_PLANT_SECONDS = 0.1
# leg lengths / s (50 cm/s on BN): a foot landing flat faster than this skids into its print
SKID_SPEED = 0.6


def lasting(flags: np.ndarray, frames: int) -> np.ndarray:
    """(F,) `flags` kept only where they hold for at least `frames` frames in a row."""
    edges = np.diff(np.concatenate([[0], flags.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    out = np.zeros(len(flags), dtype=bool)
    for a, b in zip(starts, ends):
        if b - a >= frames:
            out[a:b] = True
    return out


def flat_foot_contacts(motion: Motion, positions: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(F, 2) contacts and horizontal foot speeds (the slower of ankle and toe). Contact: ankle and toe
    both near their floor for at least MIN_PLANT_SECONDS, this frame and the one before (so the last
    fall onto the floor is not sliding); either alone also catches the low swing foot."""
    sk = motion.skeleton
    pos = motion.global_positions() if positions is None else positions
    leg = left_leg_length(sk)
    frames = max(2, round(MIN_PLANT_SECONDS * motion.fps))
    contacts, speeds = [], []
    for side in ("l", "r"):
        flat = np.ones(len(pos), dtype=bool)
        v = []
        for part in ("ankle", "toe"):
            p = pos[:, body_joint(sk, f"{part}_{side}")]
            flat &= p[:, 1] < np.percentile(p[:, 1], FLOOR_PERCENTILE) + CONTACT_MARGIN * leg
            s = np.zeros(len(p))
            s[1:] = np.linalg.norm(np.diff(p[:, [0, 2]], axis=0), axis=-1) * motion.fps
            v.append(s)
        flat = lasting(flat, frames)
        contacts.append(flat & np.concatenate([[False], flat[:-1]]))
        speeds.append(np.minimum(*v))
    return np.stack(contacts, -1), np.stack(speeds, -1)


def planted(contacts: np.ndarray, speeds: np.ndarray) -> np.ndarray:
    """The speeds (`flat_foot_contacts`) over the frames each foot is planted, feet pooled."""
    return speeds[1:][contacts[1:]]


def touchdowns(contacts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(feet, frames) of each planted stretch's first frame, foot by foot."""
    starts = contacts & ~np.concatenate([np.zeros_like(contacts[:1]), contacts[:-1]])
    feet, frames = np.nonzero(starts.T)
    return feet, frames


def touchdown_speeds(contacts: np.ndarray, speeds: np.ndarray) -> np.ndarray:
    """(N,) speed of each foot landing flat: the faster of a stretch's first two frames."""
    return np.array([speeds[a : a + 2, k].max() for k, a in zip(*touchdowns(contacts))])


def foot_skating(motion: Motion, positions: np.ndarray | None = None) -> dict:
    """Over flat-foot contacts: `skate_ratio` (share past SKATE_SPEED) and `contact_speed` (mean)."""
    contacts, speeds = flat_foot_contacts(motion, positions)
    contacts, speeds = contacts[1:], speeds[1:]
    n = int(contacts.sum())
    if n == 0:
        return {"skate_ratio": 0.0, "contact_speed": 0.0, "contact_frames": 0}
    s = speeds[contacts]
    return {
        "skate_ratio": float((s > SKATE_SPEED * left_leg_length(motion.skeleton)).mean()),
        "contact_speed": float(s.mean()),
        "contact_frames": n,
    }
