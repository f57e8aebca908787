"""Held-out numbers for the model card: reconstruction losses on validation windows with and
without the input labels, and how far unlabelled stylisation lands from labelled stylisation.

    .venv/bin/python -m models.erd.evaluate [--split val]   # prints JSON
"""

from __future__ import annotations

import argparse
import json

import torch

from ..settings import get_settings


@torch.no_grad()
def evaluate(split: str = "val") -> dict:
    from . import load
    from .dataset import WindowSampler, load_split
    from .train import Losses, one_hot_targets, real_rot

    torch.set_num_threads(1)
    model = load(get_settings().weights_dir / "erd")
    gen = model.torch_generator()
    std = torch.as_tensor(model.std, dtype=torch.float32)
    from .features import POS, ROOTVEL, VEL

    scale = {"pos": std[POS], "vel": torch.cat([std[VEL], std[ROOTVEL]])}
    losses = Losses(model.skeleton, scale)
    v = WindowSampler(load_split(split), 24).fixed(2)
    x, style, content = v["x"], v["style"], v["content"]
    real = losses.real_view(x)
    unknown = torch.full_like(style, -1)
    out: dict = {"windows": int(len(x))}
    settings = {
        "labels": (style, content),
        "no_style": (unknown, content),
        "no_content": (style, unknown),
        "no_labels": (unknown, unknown),
    }
    neutral = style == 0
    target = torch.where(neutral, 1 + torch.arange(len(style)) % 6, torch.zeros_like(style))
    transfers = {}
    for tag, (s_in, c_in) in settings.items():
        rec = gen(x, s_in, c_in, one_hot_targets(style))
        view = losses.fake_view(rec)
        rot, pos, vel = losses.recon(rec, view, real, x)
        dq = (rec["rot"] * real_rot(x)).sum(-1).abs().clamp(max=1.0)
        out[tag] = {
            "recon_rot_loss": rot.item(),
            "recon_pos_loss": pos.item(),
            "recon_vel_loss": vel.item(),
            "recon_rot_deg": torch.rad2deg(2 * torch.acos(dq)).mean().item(),
        }
        transfers[tag] = gen(x, s_in, c_in, one_hot_targets(target))["rot"]
        dq = (transfers[tag] * real_rot(x)).sum(-1).abs().clamp(max=1.0)
        out[tag]["transfer_change_deg"] = torch.rad2deg(2 * torch.acos(dq)).mean().item()
    for tag in ("no_style", "no_content", "no_labels"):
        dq = (transfers[tag] * transfers["labels"]).sum(-1).abs().clamp(max=1.0)
        ang = torch.rad2deg(2 * torch.acos(dq))
        out[tag]["transfer_vs_labelled_deg"] = ang.mean().item()
        out[tag]["transfer_vs_labelled_deg_neutral_inputs"] = ang[neutral].mean().item()
    return out


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--split", default="val")
    print(json.dumps(evaluate(ap.parse_args().split), indent=1))
