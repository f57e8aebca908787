"""A quick style probe (NOT the project's independent evaluation suite): a small temporal-conv
style classifier trained on real training windows; then whole validation neutral clips are
stylised (full-clip forward = streaming) to every target style, cut into 24-frame windows and
classified. Reports target-style accuracy for Style-ERD vs the identity baseline (input unchanged),
with and without input labels.

    .venv/bin/python -m models.erd.style_probe      # ~3 min on 1 core; prints JSON
"""

from __future__ import annotations

import json
import sys

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from ..settings import get_settings


def _classifier(in_dim: int, n: int) -> nn.Module:
    return nn.Sequential(nn.Conv1d(in_dim, 128, 5, padding=2), nn.LeakyReLU(0.2), nn.Conv1d(128, 64, 5, padding=2),
                         nn.LeakyReLU(0.2), nn.Conv1d(64, 64, 5, padding=2), nn.LeakyReLU(0.2), nn.Conv1d(64, n, 1))


def main(iters: int = 2000) -> dict:
    from ..data import build_index, load_motions, select
    from . import load
    from .dataset import STYLES, TARGET_STYLES, WindowSampler, load_split
    from .offline import stylise
    torch.set_num_threads(1)
    torch.manual_seed(0)
    model = load(get_settings().weights_dir / "erd")
    gen = model.torch_generator()
    mean, std = torch.as_tensor(model.mean, dtype=torch.float32), torch.as_tensor(model.std, dtype=torch.float32)
    prep = lambda x: ((x - mean) / std).transpose(1, 2)  # noqa: E731
    clf = _classifier(len(mean), len(STYLES))
    opt = torch.optim.Adam(clf.parameters(), lr=1e-3)
    train = WindowSampler(load_split("train"), 24, p_neutral=1 / 7, seed=5)
    for it in range(iters):
        b = train.sample(64)
        loss = F.cross_entropy(clf(prep(b["x"])).mean(-1), b["style"])
        opt.zero_grad()
        loss.backward()
        opt.step()
    clf.eval()
    out: dict = {}
    with torch.no_grad():
        v = WindowSampler(load_split("val"), 24).fixed(2)
        out["real_val_window_acc"] = (clf(prep(v["x"])).mean(-1).argmax(-1) == v["style"]).float().mean().item()
        clips = select(build_index(["bandai-namco-2"]), split="val", style="normal")
        motions = load_motions(clips)
        results = {"identity": [], "erd_labels": [], "erd_nolabels": []}
        per_style = {s: {"erd_labels": [], "erd_nolabels": []} for s in TARGET_STYLES}
        from .dataset import CONTENTS
        for clip, motion in zip(clips, motions):
            if motion.num_frames < 48:
                continue
            starts = np.linspace(0, motion.num_frames - 24, 4).round().astype(int)

            def windows(m):
                x, _ = model.maker.sequence(m.translations[:, 1], m.rotations)
                return torch.as_tensor(np.stack([x[s:s + 24] for s in starts]), dtype=torch.float32)

            base = windows(motion)
            for k, style in enumerate(TARGET_STYLES):
                tgt = STYLES.index(style)
                w = np.zeros(6)
                w[k] = 1.0
                results["identity"].append((clf(prep(base)).mean(-1).argmax(-1) == tgt).float().mean().item())
                for tag, kw in (("erd_labels", dict(style_in=0, content=CONTENTS.index(clip.content))), ("erd_nolabels", {})):
                    pred = clf(prep(windows(stylise(gen, model.maker, motion, w, **kw)))).mean(-1).argmax(-1)
                    acc = (pred == tgt).float().mean().item()
                    results[tag].append(acc)
                    per_style[style][tag].append(acc)
        out["target_style_acc"] = {k: float(np.mean(v)) for k, v in results.items()}
        out["target_style_acc_per_style"] = {s: {k: float(np.mean(v)) for k, v in d.items()} for s, d in per_style.items()}
        out["clips"] = len(motions)
    return out


if __name__ == "__main__":
    print(json.dumps(main(int(sys.argv[1]) if len(sys.argv) > 1 else 2000), indent=1))
