"""Streamed validation of LPN-FiLM weights, for choosing between training runs and snapshots.

A one-frame validation loss does not rank closed-loop controllers (the run with the lowest loss
can carry itself worst), so candidates are streamed through the runtime
on the VALIDATION split, never the test clips `make eval` scores: the dataset-2 `normal` locomotion
inputs (`pick_clips(4, LOCOMOTION, split="val")`, 13 clips) toward each common style. Per style:
both judges' style accuracy, content accuracy and what the misses were read as, the worst joint's
share of frames within the real rotation p99, planted-toe slide, and the pace (judge-free: how far
the output's hips travel against the input's).

    .venv/bin/python -m models.lpn validate [WEIGHTS_DIR ...]     # default: the committed weights
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..data import build_index, load_motions, select
from ..eval.features import clip_features
from ..eval.judges import Judges, RotationJudge, load_judges, load_rotation_judge
from ..eval.plausibility import RotationReference
from ..eval.run import DATASET, LOCOMOTION, pick_clips, score, stylise
from ..interface import StreamingModel
from ..motion.skeleton import Motion

STYLES = ("active", "elderly", "exhausted", "feminine", "masculine", "youthful")
FRAMES = 150  # 5 s at 30 fps, as `make eval`
REAL_FOR_FMD = 40  # real TRAIN clips per style for the FMD reference


def hips_travel(motion: Motion) -> float:
    """Horizontal distance between the hips' first and last positions."""
    hips = motion.skeleton.names.index("Hips")
    path = motion.global_transforms()[1][:, hips]
    return float(np.linalg.norm((path[-1] - path[0])[[0, 2]]))


def pace(outputs: list[Motion], inputs: list[Motion]) -> float:
    """Median over clips of the output's hip travel over its input's: 1 keeps up with the control,
    below 1 lags it."""
    return float(np.median([hips_travel(o) / max(hips_travel(i), 1e-6) for o, i in zip(outputs, inputs)]))


def misread(truth: list[str], predicted: list[str]) -> dict[str, int]:
    """What the wrong predictions were, as {"run->walk": count}."""
    return dict(Counter(f"{t}->{p}" for t, p in zip(truth, predicted) if t != p))


@dataclass
class Reference:
    """What a candidate is scored against, loaded once for every candidate."""

    judges: Judges
    rotation_judge: RotationJudge
    rotations: RotationReference
    latents: dict[str, np.ndarray]  # per style: real TRAIN clips' judge latents (FMD)


def load_reference(styles: tuple[str, ...] = STYLES) -> Reference:
    index = build_index([DATASET])
    real = {s: load_motions(select(index, split="train", style=s)) for s in styles}
    judges = load_judges()
    return Reference(
        judges,
        load_rotation_judge(),
        RotationReference(real),
        {s: judges.latents([clip_features(m) for m in real[s][:REAL_FOR_FMD]]) for s in styles},
    )


def validation_inputs(frames: int = FRAMES) -> tuple[list[Motion], list[str]]:
    clips = pick_clips(4, LOCOMOTION, split="val")
    return [m.slice(0, frames) for m in load_motions(clips)], [c.content for c in clips]


def validate(
    model: StreamingModel,
    ref: Reference,
    inputs: list[Motion],
    contents: list[str],
    styles: tuple[str, ...] = STYLES,
) -> dict[str, dict]:
    """Per style: `make eval`'s scores of the streamed outputs, plus `pace` and `content_misread`."""
    names = model.styles()
    out = {}
    for style in styles:
        outputs = stylise(model, inputs, [names.index(style)] * len(inputs))
        feats = [clip_features(m) for m in outputs]
        scores = score(
            ref.judges, ref.rotation_judge, ref.rotations, outputs, inputs, style, contents, ref.latents[style], feats
        )
        predicted = ref.judges.predict_content(feats)
        out[style] = {**scores, "pace": pace(outputs, inputs), "content_misread": misread(contents, predicted)}
    return out


def report_line(style: str, r: dict) -> str:
    return (
        f"{style:10s} style {r['style_acc']:.2f}  rot {r['style_acc_rot']:.2f}  content {r['content_acc']:.2f}  "
        f"within {r['rot_within_min']:.3f} {r['rot_worst_joint']:11s} slide {r['slide_toe_median']:.1f}  "
        f"pace {r['pace']:.2f}  read as {r['predicted_styles']}  content misread {r['content_misread']}"
    )


def main(weights_dirs: list[Path], frames: int = FRAMES) -> None:
    from . import load

    torch.set_num_threads(1)
    ref = load_reference()
    inputs, contents = validation_inputs(frames)
    for folder in weights_dirs:
        results = validate(load(folder), ref, inputs, contents)
        print(f"== {folder} ({len(inputs)} validation locomotion inputs, {frames} frames)")
        for style, r in results.items():
            print(report_line(style, r), flush=True)
        keys = ("style_acc", "style_acc_rot", "content_acc", "pace")
        means = [np.mean([r[k] for r in results.values()]) for k in keys]
        print("mean " + "  ".join(f"{k} {v:.3f}" for k, v in zip(keys, means)), flush=True)
