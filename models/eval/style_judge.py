"""The sealed evaluation's style judge: per-window statistics of local rotations and angular
speeds, read by a multinomial logistic regression trained on Bandai Namco datasets 1 and 2.

A different recipe from the conv-net judges (`judges.py`), so a model tuned against those gets no
free pass. No positions (bone lengths tell performers apart); each clip is read against the centre
of its own session and content. Inference is numpy; the fit is `python -m models.eval.fit_style_judge`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..motion.rotations import matrix_to_6d, quat_angle, quat_to_matrix
from ..motion.skeleton import Motion
from .plausibility import body_joints, comparable_rotations

WINDOW = 60  # frames (2 s at 30 fps): about two gait cycles
STRIDE = 30
# Standardisation floor and clip, so a model's half-degree off a hinge does not decide the read
SCALE_FLOOR = 0.05
Z_CLIP = 5.0
FILE = "style_judge.npz"
OTHER = "other"  # what `predict` answers for a style outside the evaluation's labels
OWN_PREFIX = "d1-"  # a dataset-1 style that no dataset-2 label agrees with


def frame_descriptors(motion: Motion) -> np.ndarray:
    """(F, 7 J) per frame: each body joint's rotation as 6-D (Hips without heading) and angular speed."""
    rot = comparable_rotations(motion)[:, body_joints(motion.skeleton)]
    six = matrix_to_6d(quat_to_matrix(rot)).reshape(len(rot), -1)
    speed = np.zeros(rot.shape[:2])
    speed[1:] = quat_angle(rot[1:], rot[:-1]) * motion.fps
    if len(rot) > 1:
        speed[0] = speed[1]
    return np.concatenate([six, speed], axis=1)


def window_statistics(desc: np.ndarray, window: int = WINDOW, stride: int = STRIDE) -> np.ndarray:
    """(N, 2 D) mean and std of the descriptors per window (a short clip is one window)."""
    n = len(desc)
    starts = list(range(0, max(n - window, 0) + 1, stride))
    if n > window and starts[-1] != n - window:
        starts.append(n - window)
    return np.stack([np.concatenate([desc[s : s + window].mean(0), desc[s : s + window].std(0)]) for s in starts])


def clip_statistics(motion: Motion) -> np.ndarray:
    return window_statistics(frame_descriptors(motion))


@dataclass
class StyleJudge:
    """A fitted judge: centres, standardisation, linear read, labels and the dataset-1 label mapping."""

    mean: np.ndarray
    scale: np.ndarray
    coef: np.ndarray  # (K, 2 D)
    intercept: np.ndarray  # (K,)
    labels: list[str]
    mapping: dict[str, str]
    centres: dict[str, np.ndarray]  # "dataset/content" -> (2 D,)

    def reference(self, dataset: str, content: str) -> np.ndarray:
        """The centre of `content` in `dataset`, falling back to the content's, the session's, or all."""
        if f"{dataset}/{content}" in self.centres:
            return self.centres[f"{dataset}/{content}"]
        for prefix in (None, dataset):
            same = [
                v
                for k, v in self.centres.items()
                if (k.split("/", 1)[1] == content if prefix is None else k.split("/", 1)[0] == prefix)
            ]
            if same:
                return np.mean(same, axis=0)
        return np.mean(list(self.centres.values()), axis=0)

    def log_proba(self, stats: np.ndarray, dataset: str, content: str) -> np.ndarray:
        """(K,) mean log-probability of each label over a clip's windows."""
        x = stats - self.reference(dataset, content)
        z = np.clip((x - self.mean) / self.scale, -Z_CLIP, Z_CLIP) @ self.coef.T + self.intercept
        z -= z.max(axis=1, keepdims=True)
        return (z - np.log(np.exp(z).sum(axis=1, keepdims=True))).mean(axis=0)

    @property
    def named(self) -> list[str]:
        """The labels the evaluation asks about (everything but the dataset-1-only styles)."""
        return [s for s in self.labels if not s.startswith(OWN_PREFIX)]

    def read(self, stats: np.ndarray, dataset: str, content: str) -> str:
        """A named label, or `OTHER` when the dataset-1-only styles together are likelier."""
        lp = self.log_proba(stats, dataset, content)
        p = np.exp(lp - lp.max())
        own = np.array([s.startswith(OWN_PREFIX) for s in self.labels])
        if own.any() and p[own].sum() > p[~own].max():
            return OTHER
        return self.labels[int(np.argmax(np.where(own, -np.inf, lp)))]

    def read_own(self, stats: np.ndarray, dataset: str, content: str) -> str:
        """The single likeliest label, dataset-1-only styles included."""
        return self.labels[int(np.argmax(self.log_proba(stats, dataset, content)))]

    def predict(self, motions: list[Motion], dataset: str, contents: list[str]) -> list[str]:
        """Each clip's read; `dataset`: the session the (input) clips come from, `contents`: what each does."""
        if len(contents) != len(motions):
            raise ValueError(f"{len(motions)} clips but {len(contents)} contents")
        return [self.read(clip_statistics(m), dataset, c) for m, c in zip(motions, contents)]

    def save(self, path: Path) -> None:
        keys = sorted(self.centres)
        np.savez_compressed(
            path,
            mean=self.mean,
            scale=self.scale,
            coef=self.coef,
            intercept=self.intercept,
            labels=np.array(self.labels),
            mapping=np.array([f"{k}={v}" for k, v in sorted(self.mapping.items())]),
            centre_keys=np.array(keys),
            centres=np.stack([self.centres[k] for k in keys]),
        )

    @classmethod
    def load(cls, path: Path) -> StyleJudge:
        z = np.load(path)
        return cls(
            z["mean"],
            z["scale"],
            z["coef"],
            z["intercept"],
            [str(s) for s in z["labels"]],
            dict(str(s).split("=", 1) for s in z["mapping"]),
            {str(k): v for k, v in zip(z["centre_keys"], z["centres"])},
        )


def centres_of(
    stats: list[np.ndarray], sessions: list[str], contents: list[str], styles: list[str]
) -> dict[str, np.ndarray]:
    """Per "dataset/content", the mean over styles of their clips' mean window statistics (each style once)."""
    groups: dict[str, dict[str, list[np.ndarray]]] = {}
    for s, d, c, st in zip(stats, sessions, contents, styles):
        groups.setdefault(f"{d}/{c}", {}).setdefault(st, []).append(s.mean(axis=0))
    return {k: np.mean([np.mean(v, axis=0) for v in g.values()], axis=0) for k, g in sorted(groups.items())}


def d1_label(style: str) -> str:
    """A dataset-1 style kept apart from dataset 2's labels."""
    return f"{OWN_PREFIX}{style}"


def fit_linear(
    stats: list[np.ndarray], labels: list[str], groups: list[str], c: float, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """Standardise and fit a logistic regression weighting each clip, label and dataset alike."""
    from sklearn.linear_model import LogisticRegression

    x = np.concatenate(stats)
    y = np.concatenate([[lab] * len(s) for s, lab in zip(stats, labels)])
    names = sorted(set(labels))
    count: dict[tuple[str, str], int] = {}
    for key in zip(labels, groups):
        count[key] = count.get(key, 0) + 1
    split = {lab: sum(1 for k in count if k[0] == lab) for lab in names}
    clip_w = [len(labels) / (len(names) * split[lab] * count[(lab, g)]) for lab, g in zip(labels, groups)]
    w = np.concatenate([np.full(len(s), cw / len(s)) for s, cw in zip(stats, clip_w)])
    mean, scale = x.mean(0), np.maximum(x.std(0), SCALE_FLOOR)
    clf = LogisticRegression(C=c, max_iter=3000, random_state=seed)
    clf.fit(np.clip((x - mean) / scale, -Z_CLIP, Z_CLIP), y, sample_weight=w)
    order = [list(clf.classes_).index(n) for n in names]
    return mean, scale, clf.coef_[order], clf.intercept_[order], names


def judges_file() -> Path:
    from .judges import weights_dir

    return weights_dir() / FILE


def load_style_judge(path: Path | None = None) -> StyleJudge:
    return StyleJudge.load(path if path is not None else judges_file())
