"""Metrics on motions: FMD (Fréchet distance of judge-autoencoder latents), foot skating, root-path
deviation. Recognition accuracies live in `judges.Judges`."""

from __future__ import annotations

import numpy as np

from ..motion.features import body_joint, foot_contacts, leg_length
from ..motion.skeleton import Motion

SKATE_SPEED = 0.2  # leg lengths per second of horizontal foot motion while in contact counts as skating


def frechet_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Fréchet distance between Gaussians fitted to samples a (N, D) and b (M, D)."""
    mu1, mu2 = a.mean(0), b.mean(0)
    s1, s2 = np.cov(a, rowvar=False), np.cov(b, rowvar=False)
    # tr sqrt(s1 s2) = sum sqrt(eig(sqrt(s1) s2 sqrt(s1))), all symmetric PSD
    w, v = np.linalg.eigh(s1)
    r1 = (v * np.sqrt(np.clip(w, 0, None))) @ v.T
    cross = np.sqrt(np.clip(np.linalg.eigvalsh(r1 @ s2 @ r1), 0, None)).sum()
    return float(((mu1 - mu2) ** 2).sum() + np.trace(s1) + np.trace(s2) - 2 * cross)


def foot_skating(motion: Motion, positions: np.ndarray | None = None) -> dict:
    """Contact = foot near the floor (`foot_contacts` height test, ankle or toe; speed test off, so a
    sliding planted foot still counts as in contact). Over contact frames: `skate_ratio` = share
    whose horizontal foot speed (slower of ankle and toe) exceeds SKATE_SPEED leg lengths/s, and
    `contact_speed` = mean horizontal foot speed (units/s)."""
    sk = motion.skeleton
    pos = motion.global_positions() if positions is None else positions
    contacts = foot_contacts(pos, sk, motion.fps, speed=np.inf)
    leg = leg_length(sk)
    speeds = []
    for side in ("l", "r"):
        v = []
        for part in (f"ankle_{side}", f"toe_{side}"):
            p = pos[:, body_joint(sk, part)][:, [0, 2]]
            s = np.zeros(len(p))
            s[1:] = np.linalg.norm(np.diff(p, axis=0), axis=-1) * motion.fps
            v.append(s)
        speeds.append(np.minimum(*v))
    speeds = np.stack(speeds, -1)[1:]
    contacts = contacts[1:]
    n = int(contacts.sum())
    if n == 0:
        return {"skate_ratio": 0.0, "contact_speed": 0.0, "contact_frames": 0}
    s = speeds[contacts]
    return {"skate_ratio": float((s > SKATE_SPEED * leg).mean()), "contact_speed": float(s.mean()), "contact_frames": n}


def path_deviation(source: Motion, output: Motion) -> float:
    """Mean horizontal distance between the input's and the output's root (Hips) paths after
    aligning both starts, over the common frames (units of the skeleton, cm for Bandai Namco)."""
    hips = body_joint(source.skeleton, "hips")
    n = min(source.num_frames, output.num_frames)
    a = source.global_positions()[:n, hips][:, [0, 2]]
    b = output.global_positions()[:n, hips][:, [0, 2]]
    return float(np.linalg.norm((a - a[0]) - (b - b[0]), axis=-1).mean())
