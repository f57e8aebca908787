"""Distillation targets: what the shipped pipeline (network and fitted stages) outputs for every
TRAIN neutral clip toward each target style, so a network can learn to carry the style in its own
rotations (`train.py --distill=...`).

    .venv/bin/python -m models.erd.distill .data/erd/distill.npz [models/weights/erd]

The file holds `frames` (rows of the TRAIN cache) and `targets` (frames, 6, 21, 4) float16: body
rotations per target style as the decoder outputs them (the Hips without the facing yaw).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from ..motion.rotations import quat_inv, quat_mul, yaw_quat
from ..motion.skeleton import Motion
from .dataset import DATASET, TARGET_STYLES, Split, load_split
from .features import BODY, FPS
from .gait import clip_gait
from .offline import to_world


@torch.no_grad()
def teacher_rotations(model, motion: Motion) -> np.ndarray:
    """(6, T, 21, 4) the pipeline's rotations of `motion` toward each style, streamed as one batch."""
    gen, maker = model.torch_generator().eval(), model.maker
    root_in = motion.translations[:, 1]
    x, yaw = maker.sequence(root_in, motion.rotations)
    S, T = len(TARGET_STYLES), len(x)
    eye = torch.eye(S)
    xt = torch.as_tensor(x, dtype=torch.float32)[None].expand(S, -1, -1)
    out = gen(xt, torch.full((S,), -1), torch.full((S,), -1), eye)
    rots = np.stack(
        [
            to_world(
                out["rot"][s].double().numpy(),
                out["root_vel"][s].double().numpy(),
                out["height"][s].double().numpy(),
                yaw,
                root_in[0],
            )[1]
            for s in range(S)
        ]
    )
    share = clip_gait(maker.positions(root_in, motion.rotations), FPS)
    w = eye.double().numpy()
    state = model.stages.init_state(S)
    for t in range(T):
        rot_in = np.repeat(motion.rotations[t : t + 1], S, axis=0)
        rots[:, t], state = model.stage_batch(state, rot_in, rots[:, t], w, np.full(S, share[t]))
    body = rots[:, :, BODY]
    body[:, :, 0] = quat_mul(quat_inv(yaw_quat(yaw))[None], rots[:, :, 1])  # the Hips without the facing yaw
    return body


def split_targets(model, split: Split, load: Callable[[str], Motion]) -> tuple[np.ndarray, np.ndarray]:
    """The rows of `split`'s neutral clips and their targets (rows, 6, 21, 4) float16."""
    frames, targets = [], []
    t0 = time.time()
    for i, c in enumerate(np.flatnonzero(split.style == 0)):
        motion = load(split.names[c])
        if len(motion.rotations) != split.lengths[c]:
            raise ValueError(f"{split.names[c]}: {len(motion.rotations)} frames, the split has {split.lengths[c]}")
        targets.append(teacher_rotations(model, motion).transpose(1, 0, 2, 3).astype(np.float16))
        frames.append(split.starts[c] + np.arange(split.lengths[c]))
        if i % 50 == 0:
            print(f"{i} clips, {time.time() - t0:.0f} s", flush=True)
    return np.concatenate(frames), np.concatenate(targets)


def build(out: Path, weights: Path) -> Path:
    """The targets of the TRAIN cache's neutral clips, written to `out`."""
    from ..data import build_index, load_motion, select
    from .runtime import load

    by_name = {c.name: c for c in select(build_index([DATASET]), split="train", style="normal")}
    frames, targets = split_targets(load(weights), load_split("train"), lambda name: load_motion(by_name[name]))
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez(out, frames=frames, targets=targets)
    return out


def main(argv: list[str]) -> None:
    import argparse

    from ..settings import get_settings

    parser = argparse.ArgumentParser(prog="python -m models.erd.distill", description=__doc__.split("\n\n")[0])
    parser.add_argument("out", type=Path, help="the .npz to write (e.g. .data/erd/distill.npz)")
    parser.add_argument("weights", type=Path, nargs="?", default=get_settings().weights_dir / "erd")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    print(build(args.out, args.weights))


if __name__ == "__main__":
    main(sys.argv[1:])
