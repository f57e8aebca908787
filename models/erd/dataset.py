"""Style-ERD data: Bandai Namco dataset 2 (7 styles, `normal` = neutral; 10 contents) as causal
per-frame features (features.py), cached as compact float32 arrays under `.data/erd/`.

    python -m models.erd.dataset          # build (or rebuild) the cache, ~1 min

Per split: features concatenated (frames, 216), clip starts, lengths and labels; plus the
reference rotations and the TRAIN normalisation. Training samples 24-frame windows from it.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..data import Clip, build_index, load_motions, select
from ..motion.rotations import quat_mean
from ..settings import get_settings
from .features import CONTACT, FeatureMaker

DATASET = "bandai-namco-2"
STYLES = ("normal", "active", "elderly", "exhausted", "feminine", "masculine", "youthful")  # 0 = neutral
TARGET_STYLES = STYLES[1:]  # one residual branch each
CONTENTS = (  # locomotion, raised hands, waves
    ("walk", "walk-turn-left", "walk-turn-right", "run")
    + ("raise-up-both-hands", "raise-up-left-hand", "raise-up-right-hand")
    + ("wave-both-hands", "wave-left-hand", "wave-right-hand")
)
WINDOW = 24
CACHE_VERSION = 1


def cache_dir() -> Path:
    return Path(get_settings().cache_dir) / "erd"


@dataclass
class Split:
    feats: np.ndarray  # (N, 216) float32
    starts: np.ndarray  # (C,) int64 offset of each clip
    lengths: np.ndarray  # (C,)
    style: np.ndarray  # (C,) index into STYLES
    content: np.ndarray  # (C,) index into CONTENTS
    names: list[str]


def build_cache(out: Path | None = None, clips: dict[str, list[Clip]] | None = None) -> Path:
    """The cache of `DATASET`, or of `clips` (split -> clips, normalised by its train split)."""
    out = out or cache_dir()
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    if clips is None:
        index = build_index([DATASET])
        clips = {s: select(index, split=s) for s in ("train", "val", "test")}
    motions = {s: load_motions(c) for s, c in clips.items()}
    sk = motions["train"][0].skeleton
    sample = np.concatenate([m.rotations[::4] for m in motions["train"]])
    sample = sample / np.linalg.norm(sample, axis=-1, keepdims=True)
    ref = quat_mean(sample)
    maker = FeatureMaker(sk, ref)
    meta = {"version": CACHE_VERSION, "styles": STYLES, "contents": CONTENTS}
    for split, chosen in clips.items():
        feats, starts, lengths = [], [], []
        offset = 0
        for motion in motions[split]:
            f, _ = maker.sequence(motion.translations[:, 1], motion.rotations)
            feats.append(f.astype(np.float32))
            starts.append(offset)
            lengths.append(len(f))
            offset += len(f)
        np.savez(
            out / f"{split}.npz",
            feats=np.concatenate(feats),
            starts=np.array(starts),
            lengths=np.array(lengths),
            style=np.array([STYLES.index(c.style) for c in chosen]),
            content=np.array([CONTENTS.index(c.content) for c in chosen]),
            names=np.array([c.name for c in chosen]),
        )
        meta[split] = len(chosen)
    train = np.load(out / "train.npz")["feats"]
    mean, std = train.mean(0), train.std(0)
    std = np.maximum(std, 1e-2 * std.mean())
    mean[CONTACT], std[CONTACT] = 0.5, 0.5
    np.savez(out / "stats.npz", mean=mean.astype(np.float32), std=std.astype(np.float32), ref=ref)
    meta["seconds"] = round(time.time() - t0, 1)
    (out / "meta.json").write_text(json.dumps(meta, indent=1))
    return out


def load_split(split: str, folder: Path | None = None) -> Split:
    folder = folder or cache_dir()
    if not (folder / f"{split}.npz").exists() or not (folder / "stats.npz").exists():
        build_cache(folder)
    with np.load(folder / f"{split}.npz") as z:
        return Split(z["feats"], z["starts"], z["lengths"], z["style"], z["content"], [str(n) for n in z["names"]])


HINGE_FIT_FRAMES = 60_000  # TRAIN frames (every style) the decoding's hinges are fitted from


def split_hinges(split: Split, skeleton):
    """Hinge joints of a split's real rotations: `hinges.npz` and the trainer decode with this fit."""
    from ..motion.hinge import fit_hinges
    from .features import NB, ROT

    body = split.feats[:: max(1, len(split.feats) // HINGE_FIT_FRAMES), ROT].reshape(-1, NB, 4)
    q = np.zeros((len(body), NB + 1, 4))
    q[..., 3] = 1.0  # joint_Root, static
    q[:, 1:] = body
    return fit_hinges(skeleton, q)


def load_stats(folder: Path | None = None) -> dict[str, np.ndarray]:
    folder = folder or cache_dir()
    if not (folder / "stats.npz").exists():
        build_cache(folder)
    with np.load(folder / "stats.npz") as z:
        return {k: z[k] for k in z.files}


class WindowSampler:
    """Random 24-frame windows: neutral with probability `p_neutral`, clips uniform otherwise."""

    def __init__(self, split: Split, window: int = WINDOW, p_neutral: float = 0.5, seed: int = 0):
        self.s = split
        self.window = window
        ok = split.lengths >= window
        self.neutral = np.flatnonzero(ok & (split.style == 0))
        self.styled = np.flatnonzero(ok & (split.style != 0))
        self.p_neutral = p_neutral
        self.rng = np.random.default_rng(seed)
        self.feats = torch.from_numpy(split.feats)

    def sample(self, batch: int) -> dict[str, torch.Tensor]:
        n_neutral = self.rng.binomial(batch, self.p_neutral)
        clips = np.concatenate(
            [self.rng.choice(self.neutral, n_neutral), self.rng.choice(self.styled, batch - n_neutral)]
        )
        starts = self.s.starts[clips] + (self.rng.random(batch) * (self.s.lengths[clips] - self.window + 1)).astype(
            np.int64
        )
        idx = starts[:, None] + np.arange(self.window)[None]
        return {
            "x": self.feats[torch.from_numpy(idx)],
            "idx": torch.from_numpy(idx),  # the frames' rows in the split
            "style": torch.from_numpy(self.s.style[clips]),
            "content": torch.from_numpy(self.s.content[clips]),
        }

    def fixed(self, n_per_clip: int = 2) -> dict[str, torch.Tensor]:
        """Deterministic windows (for validation): up to n_per_clip evenly spaced windows per clip."""
        idx, clips = [], []
        for c in np.concatenate([self.neutral, self.styled]):
            L = self.s.lengths[c]
            for st in np.linspace(0, L - self.window, n_per_clip).round().astype(int):
                idx.append(self.s.starts[c] + st + np.arange(self.window))
                clips.append(c)
        clip_rows = np.array(clips)
        return {
            "x": self.feats[torch.from_numpy(np.stack(idx))],
            "style": torch.from_numpy(self.s.style[clip_rows]),
            "content": torch.from_numpy(self.s.content[clip_rows]),
        }


if __name__ == "__main__":
    import argparse

    argparse.ArgumentParser(prog="python -m models.erd.dataset", description=__doc__.split("\n\n")[0]).parse_args()
    path = build_cache()
    print(path, (path / "meta.json").read_text())
