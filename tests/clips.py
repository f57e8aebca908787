"""What several tests share: a clip as the `frames` of a JSON style upload, an LPN-FiLM
controller session driven through a list of control ticks, a clip streamed through a model one
frame at a time, frames of a batch split and joined, and the angle between rotations."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from clients.sdk import Client
from models.interface import FrameBatch
from models.motion.rotations import quat_angle
from models.motion.skeleton import Motion


def frames_json(motion: Motion) -> dict:
    """The `frames` field of `POST /v1/styles`: Hips translations and local rotations per frame."""
    return {"root": motion.translations[:, 1].tolist(), "rotations": motion.rotations.tolist()}


def drive_lpn(base: str, style: str, ticks) -> np.ndarray:
    """Rotations (T, 22, 4) of a fresh LPN-FiLM session on `style`, one control tick per
    (velocity, facing, gait) in `ticks`."""
    with Client(base).session(model="lpn", style=style) as session:
        return np.array([session.control(v, facing, gait).rotations for v, facing, gait in ticks])


def stylise_stream(model, motion: Motion, weights: np.ndarray, **labels: str | None) -> Motion:
    """`motion` streamed through `model` in one fresh session (`labels`: its `init_state`'s), one
    frame per `step_batch`; `weights` (S,) or per frame (T, S)."""
    state, roots, rots = model.init_state(1, **labels), [], []
    # writable rows, as the service sends: a read-only broadcast row would compile kernels anew
    w = np.array(np.broadcast_to(np.asarray(weights, np.float64), (motion.num_frames, np.shape(weights)[-1])))
    for t in range(motion.num_frames):
        frame = FrameBatch(motion.translations[t : t + 1, 1], motion.rotations[t : t + 1])
        o, state = model.step_batch(state, frame, w[t][None])
        roots.append(o.root[0])
        rots.append(o.rotations[0])
    translations = motion.translations.copy()
    translations[:, 1] = roots
    return replace(motion, rotations=np.array(rots), translations=translations)


def streamed_rotations(model, motion: Motion, weights: np.ndarray) -> np.ndarray:
    """(T, J, 4) the output rotations of `motion` streamed through `model` with style weights (S,)."""
    return stylise_stream(model, motion, weights).rotations


def frame_row(frames: FrameBatch, i: int) -> FrameBatch:
    """Session i's frame of a batch, as a batch of one."""
    control = None if frames.control is None else frames.control[i : i + 1]
    return FrameBatch(frames.root[i : i + 1], frames.rotations[i : i + 1], control=control)


def concat_frames(frames: list[FrameBatch]) -> FrameBatch:
    """Frames of many sessions as one batch; rows without control get a zero (not given) control row."""
    control = None
    if any(f.control is not None for f in frames):
        control = np.concatenate([f.control if f.control is not None else np.zeros((len(f), 5)) for f in frames])
    return FrameBatch(
        np.concatenate([f.root for f in frames]), np.concatenate([f.rotations for f in frames]), control=control
    )


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation angle between quaternions (normalised first), degrees; q and -q are one rotation."""
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    return np.degrees(quat_angle(a, b))
