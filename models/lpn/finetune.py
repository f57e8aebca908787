"""A new LPN-FiLM style from a clip, improved: fine-tune a copy of the FiLM generator on the clip
itself with the motion network frozen.

The instant style (`LPNModel.add_style_from_clip`) can miss a style far from the training styles.
Here the clip's own training samples (`dataset.clip_samples`) go through a frozen network with
FiLM = generator(clip windows), under the training objective; the result is still a (4, H) FiLM
vector. Dropout stays on, as in training: without it the vector is brittle in closed loop.

The clip is split in time: the last `1 - fit_share` of its samples are held back (after a
30-frame gap), and their loss before and after says whether tuning helped on unseen motion.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from ..motion.features import mirror
from ..motion.skeleton import Motion
from . import features as lf
from .dataset import ClipSamples, clip_samples
from .network import CLIP_FRAMES, LPN
from .phases import style_axes
from .train import body_bones, tile_clip, training_loss

RUN_SPEED = 220.0  # cm/s: a clip whose median Hips speed is above this is a run (gait 1), as the runtime's derived gait
HORIZON = lf.FUTURE * lf.STEP  # 30 frames: how far a sample's targets reach beyond the frame it predicts

Progress = Callable[[float, float], None]  # (fraction done, current minibatch loss)


@dataclass(frozen=True)
class FineTuneConfig:
    steps: int = 300
    lr: float = 1e-4
    batch: int = 64  # fit samples per step
    windows: int = 2  # random 120-frame generator windows per step, FiLM averaged
    window_stride: int = 10  # windows of the fit part averaged into the final FiLM vector ...
    max_windows: int = 64  # ... at most this many, evenly spread (long clips)
    fit_share: float = 0.8
    w_bone: float = 1.0  # train.TrainConfig.w_bone
    seed: int = 0
    min_fit_samples: int = 30
    min_heldout_samples: int = 10
    dropout: bool = True  # the network's dropout on while tuning, as in training (see the module docstring)


@dataclass
class FineTuneResult:
    film: np.ndarray  # (4, H) FiLM vector of the fine-tuned generator on the fit part's windows
    film_before: np.ndarray  # (4, H) the same windows through the original generator
    heldout_loss_before: float
    heldout_loss_after: float
    fit_samples: int
    heldout_samples: int
    steps: int
    seconds: float

    @property
    def improved(self) -> bool:
        return self.heldout_loss_after < self.heldout_loss_before

    def summary(self) -> dict:
        return {
            "steps": self.steps,
            "seconds": round(self.seconds, 2),
            "fit_samples": self.fit_samples,
            "heldout_samples": self.heldout_samples,
            "heldout_loss_before": round(self.heldout_loss_before, 5),
            "heldout_loss_after": round(self.heldout_loss_after, 5),
            "improved": self.improved,
        }


def min_frames(cfg: FineTuneConfig = FineTuneConfig()) -> int:
    """Shortest clip leaving `min_fit_samples` to fit and `min_heldout_samples` held back."""
    n = HORIZON + 1
    while _split(n, cfg)[0] < cfg.min_fit_samples or _split(n, cfg)[1] < cfg.min_heldout_samples:
        n += 1
    return n + HORIZON + 1


def _split(n: int, cfg: FineTuneConfig) -> tuple[int, int]:
    """(fit samples, held-back samples) of a clip with n samples: fit t < c - HORIZON, held back t >= c."""
    c = int(math.ceil(cfg.fit_share * n))
    return max(c - HORIZON, 0), n - c


def clip_gait(motion: Motion) -> float:
    """1.0 (run) when the clip's median Hips speed exceeds RUN_SPEED, else 0.0 (walk)."""
    hips = motion.translations[:, lf.HIPS][:, [0, 2]]
    speed = np.linalg.norm(np.diff(hips, axis=0), axis=-1) * motion.fps
    return float(np.median(speed) > RUN_SPEED) if len(speed) else 0.0


def clip_training_samples(motion: Motion) -> ClipSamples:
    """The clip's samples as training built them (gait from its speed, phase axes from it and its mirror)."""
    return clip_samples(motion, clip_gait(motion), style_axes([motion, mirror(motion)]))


def generator_windows(feats: np.ndarray, stride: int, limit: int) -> np.ndarray:
    """At most `limit` CLIP_FRAMES windows of the generator features (tiled if short), every `stride`."""
    f = tile_clip(feats, CLIP_FRAMES)
    starts = np.arange(0, len(f) - CLIP_FRAMES + 1, stride)
    if len(starts) > limit:
        starts = starts[np.linspace(0, len(starts) - 1, limit).round().astype(int)]
    return np.stack([f[s : s + CLIP_FRAMES] for s in starts])


def fine_tune(
    net: LPN, motion: Motion, cfg: FineTuneConfig = FineTuneConfig(), progress: Progress | None = None
) -> FineTuneResult:
    """Fine-tune a copy of `net`'s generator on `motion`; deterministic per seed and thread count."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(cfg.seed)
        return _fine_tune(net, motion, cfg, progress)


def _fine_tune(net: LPN, motion: Motion, cfg: FineTuneConfig, progress: Progress | None) -> FineTuneResult:
    t0 = time.perf_counter()
    samples = clip_training_samples(motion)
    n = len(samples.X)
    n_fit, n_held = _split(n, cfg)
    if n_fit < cfg.min_fit_samples or n_held < cfg.min_heldout_samples:
        raise ValueError(f"clip too short to fine-tune: {motion.num_frames} frames, need at least {min_frames(cfg)}")
    fit, held = np.arange(n_fit), np.arange(n - n_held, n)
    fit_frames = n_fit + HORIZON + 1  # frames up to the last fit target: all the generator may see

    model = copy.deepcopy(net).eval()  # the held-back loss without dropout, as the runtime runs it
    for p in model.parameters():
        p.requires_grad_(False)
    generator = model.film
    for p in generator.parameters():
        p.requires_grad_(True)
    parents, lengths = body_bones(motion.skeleton)
    lengths_t = torch.as_tensor(lengths, dtype=torch.float32)
    X = model.normalise_x(torch.from_numpy(samples.X))
    G = model.normalise_g(torch.from_numpy(samples.G))
    Y = model.normalise_y(torch.from_numpy(samples.Y))
    feats = torch.from_numpy(samples.style_feats[:fit_frames])
    all_windows = torch.from_numpy(
        generator_windows(samples.style_feats[:fit_frames], cfg.window_stride, cfg.max_windows)
    )

    def film_of(windows: torch.Tensor) -> torch.Tensor:
        return model.style_film(windows).mean(0, keepdim=True)

    def heldout_loss() -> tuple[float, torch.Tensor]:
        with torch.no_grad():
            film = film_of(all_windows)
            loss, _, _ = training_loss(model, model(X[held], G[held], film), Y[held], parents, lengths_t, cfg.w_bone)
        return float(loss), film[0]

    before, film_before = heldout_loss()
    rng = np.random.default_rng(cfg.seed)
    tiled = torch.from_numpy(tile_clip(feats.numpy(), CLIP_FRAMES))
    opt = torch.optim.Adam(generator.parameters(), lr=cfg.lr)
    model.drop.train(cfg.dropout)
    for step in range(cfg.steps):
        starts = rng.integers(0, len(tiled) - CLIP_FRAMES + 1, cfg.windows)
        windows = torch.stack([tiled[s : s + CLIP_FRAMES] for s in starts])
        idx = torch.from_numpy(rng.choice(fit, min(cfg.batch, n_fit), replace=False))
        loss, _, _ = training_loss(
            model, model(X[idx], G[idx], film_of(windows)), Y[idx], parents, lengths_t, cfg.w_bone
        )
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if progress is not None:
            progress((step + 1) / cfg.steps, loss.item())
    model.drop.eval()
    after, film_after = heldout_loss()
    return FineTuneResult(
        film_after.numpy().copy(),
        film_before.numpy().copy(),
        before,
        after,
        n_fit,
        n_held,
        cfg.steps,
        time.perf_counter() - t0,
    )
