"""New styles from a clip, measured on the three dataset-1 styles kept out of training.

For each held-out style: `add_style_from_clip` on one of its real clips (the FiLM generator's
embedding, nothing trained), then the model is driven by the same input (a dataset-1 `normal`
walk, derived control) once in the new style and once in `normal`. The eval suite's style judge
only knows the dataset-2 styles, so the measure is a plain one: the distance between motion
statistics (per-feature mean and std over frames of the FiLM generator's clip features,
positions and velocities in the character frame, in units of the training std) of the generated
motion and of the style's real walking clips. The new style works when its output is closer to
the real style than the `normal` output is.

    .venv/bin/python -m models.lpn heldout      # prints JSON, renders out/lpn/lpn_heldout_*.png
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..data import build_index, load_motion, select
from .dataset import D1, HELD_OUT, clip_style_features

CONTENTS = ("walk",)


def motion_stats(motion, S_std: np.ndarray, skip: int = 30) -> np.ndarray:
    """Mean and std over frames of the clip features, in units of the training std (first second
    skipped: a stream starts standing)."""
    f = clip_style_features(motion)[skip:] / S_std
    return np.concatenate([f.mean(0), f.std(0)])


def evaluate(model, out_dir: Path | None = None, frames: int = 240) -> dict:
    index = build_index([D1])
    S_std = model.p["S_std"]
    source_clip = select(index, style="normal", content="walk")[0]
    source = load_motion(source_clip)
    results = {"source": source_clip.name}
    renders = []
    for name in HELD_OUT:
        style = name.removeprefix("d1-")
        clips = select(index, style=style, content=CONTENTS)
        real = [load_motion(c) for c in clips]
        reference = np.mean([motion_stats(m, S_std) for m in real], axis=0)
        model.add_style_from_clip(name, real[0])
        try:
            styled, _ = model.run(source, model.weight_vector({name: 1.0}), frames=frames)
        finally:
            model.remove_style(name)
        neutral, _ = model.run(source, model.weight_vector({"normal": 1.0}), frames=frames)
        d_new = float(np.linalg.norm(motion_stats(styled, S_std) - reference) / np.sqrt(reference.size))
        d_normal = float(np.linalg.norm(motion_stats(neutral, S_std) - reference) / np.sqrt(reference.size))
        d_real_normal = float(np.linalg.norm(motion_stats(source, S_std) - reference) / np.sqrt(reference.size))
        results[name] = {"clip": clips[0].name, "distance_new_style": round(d_new, 3),
                         "distance_normal": round(d_normal, 3), "distance_real_normal_walk": round(d_real_normal, 3)}
        renders.append((name, styled, neutral, real[0]))
    if out_dir is not None:
        from ..motion.render import render_contact_sheet
        for name, styled, neutral, real in renders:
            render_contact_sheet([real, styled, neutral], Path(out_dir) / f"lpn_heldout_{name}.png", frames=6,
                                 titles=[f"real {name}", f"{name} from clip", "normal"])
    return results
