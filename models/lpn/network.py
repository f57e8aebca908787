"""LPN-FiLM network (torch): a mixture-of-experts motion network gated by local phases, with FiLM
style modulation from a clip encoder (Mason, Starke & Komura 2022, Fig. 2).

- Gating: phase features -> 32 -> 32 -> E, ELU, softmax: the expert blend.
- Motion: X -> H -> H -> Y, each layer the gate-weighted blend of E experts' outputs; hidden
  layers: layer norm, FiLM (h * (1 + gamma) + beta), ELU; dropout on each layer's input.
- FiLM generator: two 1-D convolutions over a style clip, mean over time, a dense layer to
  (gamma1, beta1, gamma2, beta2); its last layer starts at zero (identity modulation).

The normalisation statistics are buffers, so a checkpoint is self-contained.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from . import features as lf

CLIP_FRAMES = 120  # the paper's 240-frame clips at 60 fps


@dataclass
class LPNConfig:
    x_dim: int = lf.X_DIM
    g_dim: int = lf.G_DIM
    y_dim: int = lf.Y_DIM
    style_dim: int = lf.STYLE_DIM
    hidden: int = 512
    experts: int = 8
    gating_hidden: int = 32
    filters: int = 256
    kernel: int = 25
    dropout: float = 0.3
    # the generator's convolutions normalised over their filters at every frame before the ELU (no
    # parameters): else units drift negative, saturate and every style gets one FiLM vector (MODEL_CARD)
    film_norm: bool = False


class ExpertLinear(nn.Module):
    """E weight sets (E, in, out); output = sum_e alpha_e (x W_e + b_e)."""

    def __init__(self, experts: int, n_in: int, n_out: int):
        super().__init__()
        bound = float(np.sqrt(6.0 / (n_in + n_out)))
        self.weight = nn.Parameter(torch.empty(experts, n_in, n_out).uniform_(-bound, bound))
        self.bias = nn.Parameter(torch.zeros(experts, n_out))

    def forward(self, x: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
        E, n_in, n_out = self.weight.shape
        h = (x @ self.weight.permute(1, 0, 2).reshape(n_in, E * n_out)).view(-1, E, n_out)
        return torch.einsum("be,beo->bo", alpha, h) + alpha @ self.bias


class FiLMGenerator(nn.Module):
    """Style clip (B, T, style_dim), normalised, -> FiLM parameters (B, 4, H)."""

    def __init__(self, cfg: LPNConfig):
        super().__init__()
        self.conv1 = nn.Conv1d(cfg.style_dim, cfg.filters, cfg.kernel)
        self.conv2 = nn.Conv1d(cfg.filters, cfg.filters, cfg.kernel)
        self.out = nn.Linear(cfg.filters, 4 * cfg.hidden)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)
        self.hidden = cfg.hidden
        self.norm = cfg.film_norm

    def _act(self, h: torch.Tensor) -> torch.Tensor:
        if self.norm:  # over the filters (dim 1) at each frame: a clip's mean over time is kept
            h = F.layer_norm(h.transpose(1, 2), h.shape[1:2]).transpose(1, 2)
        return F.max_pool1d(F.elu(h), 2)

    def forward(self, clip: torch.Tensor) -> torch.Tensor:
        h = self._act(self.conv1(clip.transpose(1, 2)))
        h = self._act(self.conv2(h))
        return self.out(h.mean(-1)).view(-1, 4, self.hidden)


class LPN(nn.Module):
    # buffers (`register_buffer` below), typed for mypy
    X_mean: torch.Tensor
    X_std: torch.Tensor
    Y_mean: torch.Tensor
    Y_std: torch.Tensor
    S_mean: torch.Tensor
    S_std: torch.Tensor
    G_scale: torch.Tensor

    def __init__(self, cfg: LPNConfig, stats: dict[str, np.ndarray] | None = None):
        super().__init__()
        self.cfg = cfg
        H, E = cfg.hidden, cfg.experts
        self.gating = nn.Sequential(
            nn.Linear(cfg.g_dim, cfg.gating_hidden),
            nn.ELU(),
            nn.Linear(cfg.gating_hidden, cfg.gating_hidden),
            nn.ELU(),
            nn.Linear(cfg.gating_hidden, E),
        )
        self.l1 = ExpertLinear(E, cfg.x_dim, H)
        self.l2 = ExpertLinear(E, H, H)
        self.l3 = ExpertLinear(E, H, cfg.y_dim)
        self.film = FiLMGenerator(cfg)
        self.drop = nn.Dropout(cfg.dropout)
        for name, dim in (
            ("X_mean", cfg.x_dim),
            ("X_std", cfg.x_dim),
            ("Y_mean", cfg.y_dim),
            ("Y_std", cfg.y_dim),
            ("S_mean", cfg.style_dim),
            ("S_std", cfg.style_dim),
        ):
            init = torch.zeros(dim) if name.endswith("mean") else torch.ones(dim)
            self.register_buffer(name, init)
        self.register_buffer("G_scale", torch.ones(()))
        if stats is not None:
            for k, v in stats.items():
                getattr(self, k).copy_(torch.as_tensor(v, dtype=torch.float32))

    # ---- normalisation
    def normalise_x(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.X_mean) / self.X_std

    def normalise_g(self, g: torch.Tensor) -> torch.Tensor:
        return g / self.G_scale

    def normalise_y(self, y: torch.Tensor) -> torch.Tensor:
        return (y - self.Y_mean) / self.Y_std

    def denormalise_y(self, y: torch.Tensor) -> torch.Tensor:
        return y * self.Y_std + self.Y_mean

    def normalise_clip(self, s: torch.Tensor) -> torch.Tensor:
        return (s - self.S_mean) / self.S_std

    # ---- forward
    def style_film(self, clip: torch.Tensor) -> torch.Tensor:
        """Raw style clip features (B, T, style_dim) -> FiLM (B, 4, H)."""
        return self.film(self.normalise_clip(clip))

    def forward(self, xn: torch.Tensor, gn: torch.Tensor, film: torch.Tensor) -> torch.Tensor:
        """Normalised input (B, X), gating input (B, G), FiLM (B|1, 4, H) -> normalised output (B, Y)."""
        alpha = torch.softmax(self.gating(gn), dim=-1)
        h = self.l1(self.drop(xn), alpha)
        h = F.elu(F.layer_norm(h, h.shape[-1:]) * (1 + film[:, 0]) + film[:, 1])
        h = self.l2(self.drop(h), alpha)
        h = F.elu(F.layer_norm(h, h.shape[-1:]) * (1 + film[:, 2]) + film[:, 3])
        return self.l3(self.drop(h), alpha)


def bone_length_loss(y: torch.Tensor, parents: np.ndarray, lengths: torch.Tensor) -> torch.Tensor:
    """Mean squared relative bone-length error of the predicted pose y (B, Y_DIM)."""
    pos = y[:, lf.POSE_OUT].view(-1, lf.NB, lf.POSE_CH)[..., :3]
    child = np.flatnonzero(parents >= 0)
    d = (pos[:, child] - pos[:, parents[child]]).norm(dim=-1)
    return ((d - lengths[child]) / lengths[child].mean()).pow(2).mean()
