"""The conv-net style and content judges, their weights file and clip-level scoring."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn

from ..settings import get_settings
from .features import FEATURE_DIM, windows

CLF_WINDOW = 32  # ~1.07 s at 30 fps
CLF_STRIDE = 8
WEIGHTS_FILE = "judges.pt"


def weights_dir() -> Path:
    return get_settings().weights_dir / "eval"


class Classifier(nn.Module):
    """1-D temporal conv net over a window of per-frame features -> class logits."""

    def __init__(self, n_classes: int, in_dim: int = FEATURE_DIM, width: int = 96, dropout: float = 0.3):
        super().__init__()
        self.net = nn.Sequential(
            nn.Dropout(0.1),
            nn.Conv1d(in_dim, width, 5, padding=2),
            nn.ReLU(),
            nn.Conv1d(width, width, 5, padding=2, stride=2),
            nn.ReLU(),
            nn.Conv1d(width, width, 3, padding=1),
            nn.ReLU(),
            nn.AdaptiveAvgPool1d(1),
            nn.Flatten(),
            nn.Dropout(dropout),
            nn.Linear(width, n_classes),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # x (N, T, D) normalised
        return self.net(x.transpose(1, 2))


@torch.no_grad()
def clip_logprobs(clf: Classifier, norm: Callable[[np.ndarray], torch.Tensor], feats: list[np.ndarray]) -> np.ndarray:
    """Per clip: mean log-probability over its sliding 1 s windows -> (N, classes)."""
    wins = [windows(f, CLF_WINDOW, CLF_STRIDE) for f in feats]
    counts = [len(w) for w in wins]
    logp = torch.log_softmax(clf(norm(np.concatenate(wins))), -1).numpy()
    out, k = [], 0
    for c in counts:
        out.append(logp[k : k + c].mean(0))
        k += c
    return np.stack(out)


@dataclass
class Judges:
    mean: np.ndarray
    std: np.ndarray
    styles: list[str]
    contents: list[str]
    style_clf: Classifier
    content_clf: Classifier
    meta: dict = field(default_factory=dict)

    def norm(self, x: np.ndarray) -> torch.Tensor:
        return torch.as_tensor((x - self.mean) / self.std, dtype=torch.float32)

    def style_logprobs(self, feats: list[np.ndarray]) -> np.ndarray:
        return clip_logprobs(self.style_clf, self.norm, feats)

    def predict_style(self, feats: list[np.ndarray]) -> list[str]:
        return [self.styles[i] for i in self.style_logprobs(feats).argmax(-1)]

    def predict_content(self, feats: list[np.ndarray]) -> list[str]:
        return [self.contents[i] for i in clip_logprobs(self.content_clf, self.norm, feats).argmax(-1)]

    def save(self, folder: Path) -> Path:
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / WEIGHTS_FILE
        half = lambda m: {k: v.half() for k, v in m.state_dict().items()}  # noqa: E731  (small file)
        torch.save(
            {
                "mean": self.mean,
                "std": self.std,
                "styles": self.styles,
                "contents": self.contents,
                "style_clf": half(self.style_clf),
                "content_clf": half(self.content_clf),
                "meta": self.meta,
            },
            path,
        )
        return path


def load_judges(folder: Path | None = None) -> Judges:
    folder = Path(folder) if folder is not None else weights_dir()
    z = torch.load(folder / WEIGHTS_FILE, weights_only=False)
    style_clf, content_clf = Classifier(len(z["styles"])), Classifier(len(z["contents"]))
    for net, key in ((style_clf, "style_clf"), (content_clf, "content_clf")):
        net.load_state_dict({k: v.float() for k, v in z[key].items()})
        net.eval()
    return Judges(
        np.asarray(z["mean"], np.float32),
        np.asarray(z["std"], np.float32),
        list(z["styles"]),
        list(z["contents"]),
        style_clf,
        content_clf,
        z.get("meta", {}),
    )
