"""Style-ERD networks (Tao et al. 2022), written for this project: generator, FT-Att discriminator
and the instance-normalised content classifier of the perceptual loss.

Generator, per frame t of a window (all causal; the LSTMs only carry the past):
    z_t    = Enc([x_t normalised, input-style one-hot (7, zeros = unknown), content one-hot (10, zeros = unknown)])
    n_t    = LSTM_neutral(z_<=t; h0, c0 = learned per content, or the learned "unknown content" state)
    r_t^s  = LSTM_s(z_<=t; h0, c0 = learned per style s)                for the 6 target styles
    l_t    = n_t + sum_s w_s r_t^s                                      (w: style weight vector)
    y_t    = Dec([l_t, w])  -> rotation offsets (21 x 4), root velocity offset (3), Hips height offset (1)
Outputs are the input plus the offsets: our skip connection (not the paper's) keeps content and
timing for free, so a short training budget goes into style.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from ..motion.skeleton import fk_torch
from .features import FEATURE_DIM, NB, POS, ROOTVEL, ROT

N_STYLES = 7  # input styles incl. neutral
N_TARGETS = 6  # residual branches
N_CONTENTS = 10


@dataclass
class ERDConfig:
    latent: int = 32  # encoder output = LSTM hidden size
    enc_hidden: int = 128
    dec_hidden: int = 128
    neutral_layers: int = 2
    style_layers: int = 2
    disc_feature: int = 16
    classifier_width: int = 64


class Generator(nn.Module):
    def __init__(self, cfg: ERDConfig, mean: np.ndarray, std: np.ndarray):
        super().__init__()
        self.cfg = cfg
        L = cfg.latent
        self.register_buffer("mean", torch.as_tensor(mean, dtype=torch.float32))
        self.register_buffer("std", torch.as_tensor(std, dtype=torch.float32))
        self.encoder = nn.Sequential(
            nn.Linear(FEATURE_DIM + N_STYLES + N_CONTENTS, cfg.enc_hidden),
            nn.ReLU(),
            nn.Linear(cfg.enc_hidden, cfg.enc_hidden),
            nn.ReLU(),
            nn.Linear(cfg.enc_hidden, L),
        )
        self.neutral = nn.LSTM(L, L, cfg.neutral_layers, batch_first=True)
        self.neutral_h0 = nn.Parameter(torch.zeros(N_CONTENTS + 1, cfg.neutral_layers, L))  # last = unknown content
        self.neutral_c0 = nn.Parameter(torch.zeros(N_CONTENTS + 1, cfg.neutral_layers, L))
        self.branches = nn.ModuleList(nn.LSTM(L, L, cfg.style_layers, batch_first=True) for _ in range(N_TARGETS))
        self.style_h0 = nn.Parameter(torch.zeros(N_TARGETS, cfg.style_layers, L))
        self.style_c0 = nn.Parameter(torch.zeros(N_TARGETS, cfg.style_layers, L))
        self.decoder = nn.Sequential(
            nn.Linear(L + N_TARGETS, cfg.dec_hidden),
            nn.ReLU(),
            nn.Linear(cfg.dec_hidden, cfg.dec_hidden),
            nn.ReLU(),
            nn.Linear(cfg.dec_hidden, 4 * NB + 3 + 1),
        )
        last = self.decoder[-1]
        assert isinstance(last, nn.Linear)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)

    def forward(
        self, x: torch.Tensor, style_in: torch.Tensor, content: torch.Tensor, weights: torch.Tensor
    ) -> dict[str, torch.Tensor]:
        """x (B, T, 216) raw features; labels (B,) or -1 = unknown; weights (B, 6) or (B, T, 6)."""
        return self.forward_multi(x, style_in, content, [weights])[0]

    def forward_multi(self, x, style_in, content, weight_sets: list[torch.Tensor]) -> list[dict[str, torch.Tensor]]:
        """Several target-weight sets for the same input: the encoder and every LSTM run once."""
        B, T, _ = x.shape
        s1 = F.one_hot(style_in.clamp_min(0), N_STYLES).float() * (style_in >= 0).float()[:, None]
        c1 = F.one_hot(content.clamp_min(0), N_CONTENTS).float() * (content >= 0).float()[:, None]
        labels = torch.cat([s1, c1], -1)[:, None].expand(B, T, -1)
        z = self.encoder(torch.cat([(x - self.mean) / self.std, labels], -1))
        ci = torch.where(content >= 0, content, torch.full_like(content, N_CONTENTS))
        h0 = self.neutral_h0[ci].transpose(0, 1).contiguous()
        c0 = self.neutral_c0[ci].transpose(0, 1).contiguous()
        neutral, _ = self.neutral(z, (h0, c0))
        branches = []
        for s, branch in enumerate(self.branches):
            hs = self.style_h0[s][:, None].expand(-1, B, -1).contiguous()
            cs = self.style_c0[s][:, None].expand(-1, B, -1).contiguous()
            branches.append(branch(z, (hs, cs))[0])
        outs = []
        for weights in weight_sets:
            if weights.dim() == 2:
                weights = weights[:, None].expand(B, T, -1)
            latent = neutral
            for s, r in enumerate(branches):
                latent = latent + weights[..., s : s + 1] * r
            y = self.decoder(torch.cat([latent, weights], -1))
            rot = (x[..., ROT] + y[..., : 4 * NB]).reshape(B, T, NB, 4)
            rot = rot / rot.norm(dim=-1, keepdim=True).clamp_min(1e-6)
            root_vel = x[..., ROOTVEL] + y[..., 4 * NB : 4 * NB + 3]
            height = x[..., POS][..., 1] + y[..., -1]  # POS starts with the Hips: its y is the height
            outs.append({"rot": rot, "root_vel": root_vel, "height": height})
        return outs


def fk_local(rot: torch.Tensor, height: torch.Tensor, offsets: torch.Tensor, parents) -> torch.Tensor:
    """Facing-frame joint positions (..., 21, 3) from body rotations (..., 21, 4) and Hips heights."""
    ident = torch.zeros(rot.shape[:-2] + (1, 4), dtype=rot.dtype, device=rot.device)
    ident[..., 3] = 1.0
    full = torch.cat([ident, rot], -2)
    trans = offsets.expand(rot.shape[:-2] + offsets.shape).clone()
    trans[..., 1, :] = 0.0
    trans[..., 1, 1] = height
    return fk_torch(full, trans, parents)[1][..., 1:, :]


def window_motion(
    pos: torch.Tensor, root_vel: torch.Tensor, rot: torch.Tensor, fps: float = 30.0
) -> dict[str, torch.Tensor]:
    """The discriminator's / classifier's view of a window: positions, velocities, rotations."""
    vel = (pos[:, 1:] - pos[:, :-1]) * fps
    return {
        "pos": pos[:, 1:].flatten(2),
        "vel": torch.cat([vel.flatten(2), root_vel[:, 1:]], -1),
        "rot": rot[:, 1:].flatten(2),
    }


def _conv(cin: int, cout: int, k: int) -> nn.Sequential:
    return nn.Sequential(nn.ReplicationPad1d(((k - 1) // 2, k - 1 - (k - 1) // 2)), nn.Conv1d(cin, cout, k))


class FTAttDiscriminator(nn.Module):
    """Temporal conv features (F x T) weighted by feature x temporal attention from the labels, summed."""

    def __init__(self, cfg: ERDConfig, in_dim: int, frames: int, scale: dict[str, torch.Tensor]):
        super().__init__()
        self.scale = scale
        dims = [in_dim, 96, 64, 48]
        layers = []
        for a, b in zip(dims[:-1], dims[1:]):
            layers += [_conv(a, b, 3), nn.LeakyReLU(0.2)]
        self.features = nn.Sequential(*layers, _conv(dims[-1], cfg.disc_feature, 3))
        self.att = nn.Sequential(
            nn.Linear(N_STYLES + N_CONTENTS, 64), nn.LeakyReLU(0.2), nn.Linear(64, 64), nn.LeakyReLU(0.2)
        )
        self.feature_att = nn.Linear(64, cfg.disc_feature)
        self.temporal_att = nn.Linear(64, frames)

    def prepare(self, view: dict[str, torch.Tensor]) -> torch.Tensor:
        return torch.cat([view["pos"] / self.scale["pos"], view["vel"] / self.scale["vel"]], -1).transpose(1, 2)

    def forward(self, inp: torch.Tensor, style: torch.Tensor, content: torch.Tensor) -> torch.Tensor:
        feat = self.features(inp)  # (B, F, T)
        a = self.att(torch.cat([F.one_hot(style, N_STYLES), F.one_hot(content, N_CONTENTS)], -1).float())
        att = self.feature_att(a)[:, :, None] * self.temporal_att(a)[:, None, :]  # outer product (B, F, T)
        return (feat * att).sum((1, 2))


class ContentClassifier(nn.Module):
    """Temporal convs with instance norm -> content logits; its activations are the perceptual features."""

    def __init__(self, cfg: ERDConfig, in_dim: int, scale: dict[str, torch.Tensor]):
        super().__init__()
        self.scale = scale
        w = cfg.classifier_width
        self.blocks = nn.ModuleList(
            [
                nn.Sequential(_conv(in_dim, w * 2, 5), nn.InstanceNorm1d(w * 2), nn.LeakyReLU(0.2)),
                nn.Sequential(_conv(w * 2, w, 5), nn.InstanceNorm1d(w), nn.LeakyReLU(0.2)),
                nn.Sequential(_conv(w, w, 5), nn.InstanceNorm1d(w), nn.LeakyReLU(0.2)),
            ]
        )
        self.head = _conv(w, N_CONTENTS, 5)

    def prepare(self, view: dict[str, torch.Tensor]) -> torch.Tensor:
        return torch.cat([view["rot"], view["pos"] / self.scale["pos"], view["vel"] / self.scale["vel"]], -1).transpose(
            1, 2
        )

    def forward(self, inp: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
        feats = []
        h = inp
        for block in self.blocks:
            h = block(h)
            feats.append(h)
        return self.head(h).mean(-1), feats
