"""Fitting an uploaded Style-ERD style's residual branch from its one clip (the upload's job).

The clip has no neutral twin, so the branch is fitted on statistics: the nearest trained style's
branch is trained (the rest frozen) so that streaming the dataset-2 TRAIN `normal` clips nearest
the upload (`descriptor`: speed and turning) puts out the clip's position and velocity statistics.
It is kept only if the `HOLDOUT` pairs come closer than with the copy; the stages are refitted.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Any

import numpy as np

from ..interface import Progress
from ..motion.skeleton import Motion
from ..motion.style_carry import tangent_stats
from .dataset import DATASET, STYLES
from .features import FPS, NB, POS, ROOTVEL, ROT
from .upload_stages import SOURCE_FRAMES, clip_rotations, descriptor, fit_stages
from .uploads import Upload

PAIRS, HOLDOUT = 10, 2  # neutral clips paired with the upload, of which held back
WINDOW, BATCH = 48, 12
STEPS, LR, SEED = 150, 3e-3, 0
SCALE_FLOOR = 0.05  # of a statistic's scale, as the style judge floors its standardisation


def neutral_motions() -> list[Motion]:
    """Every dataset-2 TRAIN `normal` clip, from the mocap (unpacked on first use)."""
    from ..data import build_index, load_motions, select

    return load_motions(select(build_index([DATASET]), dataset=DATASET, split="train", style=STYLES[0]))


def features(maker, motions: list[Motion]) -> list[np.ndarray]:
    """Features (F, 216) of each clip, by `maker` (the model's)."""
    return [maker.sequence(m.translations[:, 1], m.rotations)[0].astype(np.float32) for m in motions]


def pair_order(clips: list[np.ndarray], x_clip: np.ndarray, k: int) -> list[int]:
    """The `k` neutral clips (longer than a window) with descriptors nearest the clip's, nearest first."""
    desc = np.stack([descriptor(c) for c in clips])
    scale = np.maximum(desc.std(0), 1e-6)
    order = np.argsort(np.linalg.norm((desc - descriptor(x_clip)) / scale, axis=1))
    return [int(i) for i in order if len(clips[i]) > WINDOW][:k]


class Branch:
    """The frozen network with one trainable branch, in torch."""

    def __init__(self, model, start: Upload) -> None:
        import torch

        self.torch = torch
        self.gen = model.torch_generator()
        for p in self.gen.parameters():
            p.requires_grad_(False)
        self.lstm = torch.nn.LSTM(model.H, model.H, model.Ln, batch_first=True)
        self.lstm.load_state_dict({k: torch.as_tensor(v, dtype=torch.float32) for k, v in start.lstm.items()})
        self.h0 = torch.nn.Parameter(torch.as_tensor(start.h0, dtype=torch.float32).clone())
        self.c0 = torch.nn.Parameter(torch.as_tensor(start.c0, dtype=torch.float32).clone())
        self.code = torch.nn.Parameter(torch.as_tensor(start.code, dtype=torch.float32).clone())
        self.offsets = torch.as_tensor(model.skeleton.offsets, dtype=torch.float32)
        self.parents = model.skeleton.parents

    def parameters(self) -> list:
        return [*self.lstm.parameters(), self.h0, self.c0, self.code]

    def positions(self, x):
        """Joint positions (B, T, 21, 3), facing frame, and root velocity (B, T, 3) for features `x`."""
        from .model import N_CONTENTS, N_STYLES, fk_local

        torch, gen = self.torch, self.gen
        B, T, _ = x.shape
        z = gen.encoder(torch.cat([(x - gen.mean) / gen.std, x.new_zeros(B, T, N_STYLES + N_CONTENTS)], -1))
        expand = lambda s: s[:, None].expand(-1, B, -1).contiguous()  # noqa: E731
        neutral, _ = gen.neutral(z, (expand(gen.neutral_h0[N_CONTENTS]), expand(gen.neutral_c0[N_CONTENTS])))
        own, _ = self.lstm(z, (expand(self.h0), expand(self.c0)))
        y = gen.decoder(torch.cat([neutral + own, self.code.expand(B, T, -1)], -1))
        rot = (x[..., ROT] + y[..., : 4 * NB]).reshape(B, T, NB, 4)
        rot = rot / rot.norm(dim=-1, keepdim=True).clamp_min(1e-6)
        height = x[..., POS][..., 1] + y[..., -1]
        root_vel = x[..., ROOTVEL] + y[..., 4 * NB : 4 * NB + 3]
        return fk_local(rot, height, self.offsets, self.parents), root_vel, rot

    def upload(self, start: Upload) -> Upload:
        lstm = {k: v.detach().numpy().copy() for k, v in self.lstm.state_dict().items()}
        h0, c0, code = (p.detach().numpy().copy() for p in (self.h0, self.c0, self.code))
        return replace(start, lstm=lstm, h0=h0, c0=c0, code=code)


def statistics(pos, root_vel, rot):
    """Per joint and axis, mean and spread of positions, velocities, rotations and angular speeds."""
    torch = __import__("torch")
    vel = (pos[:, 1:] - pos[:, :-1]) * FPS
    dot = (rot[:, 1:] * rot[:, :-1]).sum(-1).abs().clamp(max=1.0)
    speed = 2.0 * (1.0 - dot.pow(2) + 1e-8).sqrt() * FPS  # ~ the angle turned per second
    parts = [pos.flatten(0, 1), vel.flatten(0, 1), root_vel.flatten(0, 1), rot.flatten(0, 1), speed.flatten(0, 1)]
    return torch.cat([torch.cat([p.mean(0).flatten(), p.std(0).flatten()]) for p in parts])


def real_statistics(x):
    """`statistics` of real frames' features (B, T, 216)."""
    B, T, _ = x.shape
    return statistics(x[..., POS].reshape(B, T, NB, 3), x[..., ROOTVEL], x[..., ROT].reshape(B, T, NB, 4))


def windows(clips: list[np.ndarray], rng: np.random.Generator, n: int) -> np.ndarray:
    picks = rng.integers(len(clips), size=n)
    return np.stack([clips[i][s : s + WINDOW] for i in picks for s in [rng.integers(len(clips[i]) - WINDOW + 1)]])


def every_window(clips: list[np.ndarray]) -> np.ndarray:
    return np.stack([c[s : s + WINDOW] for c in clips for s in range(0, len(c) - WINDOW + 1, WINDOW // 2)])


def fine_tune(model, start: Upload, clip, progress: Progress) -> tuple[Upload | None, dict[str, Any]]:
    """The branch fitted from `clip` and the job's figures; None if the held-back clips came no closer."""
    import torch

    t0 = time.perf_counter()
    torch.manual_seed(SEED)
    rng = np.random.default_rng(SEED)
    x_clip, _ = model.maker.sequence(clip.translations[:, 1], clip.rotations)
    progress(0.03, "pairing neutral clips of the same pace and turning")
    motions = neutral_motions()
    feats = features(model.maker, motions)
    order = pair_order(feats, x_clip, PAIRS)
    neutral = [feats[i] for i in order]
    train, held = neutral[:-HOLDOUT], neutral[-HOLDOUT:]
    branch = Branch(model, start)
    target = real_statistics(torch.as_tensor(x_clip[None], dtype=torch.float32))
    each = torch.stack([real_statistics(torch.as_tensor(c[None], dtype=torch.float32)) for c in neutral])
    scale = each.std(0).clamp_min(SCALE_FLOOR)  # how much one neutral clip's statistics vary from another's
    held_x = torch.as_tensor(every_window(held), dtype=torch.float32)

    def loss(x) -> Any:
        return (((statistics(*branch.positions(x)) - target) / scale) ** 2).mean()

    with torch.no_grad():
        before = float(loss(held_x))
    opt = torch.optim.Adam(branch.parameters(), lr=LR)
    for step in range(STEPS):
        x = torch.as_tensor(windows(train, rng, BATCH), dtype=torch.float32)
        value = loss(x)
        opt.zero_grad()
        value.backward()
        opt.step()
        if step % 10 == 0:
            progress(0.05 + 0.75 * step / STEPS, f"fitting the residual branch: loss {float(value.detach()):.3f}")
    with torch.no_grad():
        after = float(loss(held_x))
    summary: dict[str, Any] = {"held_out_loss_start": round(before, 4), "held_out_loss_fitted": round(after, 4)}
    summary["paired_clips"] = len(neutral)
    if not after < before:
        summary["seconds"] = round(time.perf_counter() - t0, 1)
        return None, summary
    tuned = branch.upload(start)
    progress(0.82, "measuring what the fitted branch makes, for the output prior")
    tuned = refit_stages(model, tuned, clip, [motions[i] for i in order])
    summary["seconds"] = round(time.perf_counter() - t0, 1)
    progress(0.98, "installing the fitted branch")
    return tuned, summary


def refit_stages(model, tuned: Upload, clip, paired: list[Motion]) -> Upload:
    """`tuned`'s stages refitted from what its own branch makes of the `paired` neutral clips."""
    from ..eval.run import stylise
    from ..motion.rotation_ball import comparable

    twin = model.network_only("fit", tuned)
    inputs = [m.slice(0, SOURCE_FRAMES) for m in paired]
    made = stylise(twin, inputs, [twin.styles().index("fit")] * len(inputs))
    mean, cov, _ = tangent_stats(comparable(np.concatenate([o.rotations for o in made])))
    q, _ = clip_rotations(model, clip)
    return replace(tuned, stages=fit_stages(model.built_in.stages, model.skeleton, q, (mean, cov)))
