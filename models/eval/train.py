"""Train the evaluation judges on the real TRAIN split of Bandai Namco dataset 2 and report their
reference accuracy on real validation and TEST clips.

    .venv/bin/python -m models.eval.train [--iters 3000]     # a few minutes on 1 CPU core
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from ..data import build_index, load_motions, select
from .features import clip_features, pad_to
from .judges import CLF_WINDOW, Classifier, Judges, weights_dir

DATASET = "bandai-namco-2"


def load_split(split: str) -> tuple[list[np.ndarray], list[str], list[str]]:
    clips = select(build_index([DATASET]), split=split)
    motions = load_motions(clips)
    return [clip_features(m) for m in motions], [c.style for c in clips], [c.content for c in clips]


class Sampler:
    """Random windows, class-balanced (pick a class, then a clip of it, then a start)."""

    def __init__(self, feats: list[np.ndarray], labels: list[int], window: int, seed: int):
        self.feats = [pad_to(f, window) for f in feats]
        self.window = window
        self.by_class = [np.flatnonzero(np.asarray(labels) == k) for k in range(max(labels) + 1)]
        self.rng = np.random.default_rng(seed)

    def sample(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        ys = self.rng.integers(len(self.by_class), size=n)
        xs = []
        for y in ys:
            f = self.feats[self.rng.choice(self.by_class[y])]
            s = self.rng.integers(len(f) - self.window + 1)
            xs.append(f[s : s + self.window])
        return np.stack(xs), ys


Norm = Callable[[np.ndarray], torch.Tensor]


def normaliser(mean: np.ndarray, std: np.ndarray) -> Norm:
    """The judges' input normalisation (`Judges.norm`), before the judges exist."""
    return lambda x: torch.as_tensor((x - mean) / std, dtype=torch.float32)


def train_classifier(
    norm: Norm, feats: list[np.ndarray], labels: list[int], n_classes: int, iters: int, seed: int, desc: str
) -> Classifier:
    torch.manual_seed(seed)
    clf = Classifier(n_classes, in_dim=feats[0].shape[1])
    opt = torch.optim.AdamW(clf.parameters(), lr=2e-3, weight_decay=1e-2)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=2e-3, total_steps=iters)
    sampler = Sampler(feats, labels, CLF_WINDOW, seed)
    clf.train()
    for _ in tqdm(range(iters), desc=desc, mininterval=5):
        batch, y = sampler.sample(128)
        x = norm(batch)
        x = x + 0.05 * torch.randn_like(x)
        loss = F.cross_entropy(clf(x), torch.as_tensor(y), label_smoothing=0.05)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
    return clf.eval()


def accuracy(judges: Judges, feats: list[np.ndarray], styles: list[str], contents: list[str]) -> dict:
    ps, pc = judges.predict_style(feats), judges.predict_content(feats)
    per_style = {s: float(np.mean([p == t for p, t in zip(ps, styles) if t == s])) for s in judges.styles}
    return {
        "clips": len(feats),
        "style_acc": float(np.mean([p == t for p, t in zip(ps, styles)])),
        "content_acc": float(np.mean([p == t for p, t in zip(pc, contents)])),
        "style_acc_per_style": per_style,
    }


def main(iters: int = 3000) -> dict:
    torch.set_num_threads(1)
    t0 = time.time()
    feats, styles, contents = load_split("train")
    style_names, content_names = sorted(set(styles)), sorted(set(contents))
    frames = np.concatenate(feats)
    mean, std = frames.mean(0), np.maximum(frames.std(0), 1e-2 * frames.std(0).max() + 1e-6)
    norm = normaliser(mean, std)
    print(f"train: {len(feats)} clips, {len(frames)} frames, loaded in {time.time() - t0:.0f}s")
    style_clf = train_classifier(
        norm, feats, [style_names.index(s) for s in styles], len(style_names), iters, 1, "style"
    )
    content_clf = train_classifier(
        norm, feats, [content_names.index(c) for c in contents], len(content_names), iters, 2, "content"
    )
    judges = Judges(mean, std, style_names, content_names, style_clf, content_clf)
    report: dict = {"train_clips": len(feats), "iters": iters}
    for split in ("val", "test"):
        f, s, c = load_split(split)
        report[split] = accuracy(judges, f, s, c)
    report["train_seconds"] = round(time.time() - t0, 1)
    judges.meta = report
    path = judges.save(weights_dir())
    (weights_dir() / "reference.json").write_text(json.dumps(report, indent=1) + "\n")
    print(json.dumps(report, indent=1))
    print(f"saved {path} ({path.stat().st_size / 1024:.0f} KiB)")
    return report


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--iters", type=int, default=1500)
    main(ap.parse_args().iters)
