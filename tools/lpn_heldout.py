"""New styles from a clip, measured on the three dataset-1 styles kept out of training: the
generator's embedding of one clip and a vector fine-tuned on it, each driving a dataset-1 walk,
against `normal`, by the distance of motion statistics to the style's real walks (the judges know
only dataset 2's styles).

    .venv/bin/python -m tools.lpn_heldout [--steps 300 --seed 0]   # JSON, out/lpn/lpn_heldout_*.png (~2 min)
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from models.data import build_index, load_motion, select
from models.lpn import load
from models.lpn.dataset import D1, HELD_OUT, clip_style_features
from models.lpn.finetune import FineTuneConfig, fine_tune
from models.lpn.runtime import LPNModel
from models.motion.render import render_contact_sheet
from models.motion.skeleton import Motion
from models.settings import REPO_ROOT, get_settings

CONTENTS = ("walk",)


def motion_stats(motion: Motion, S_std: np.ndarray, skip: int = 30) -> np.ndarray:
    """Mean and std over frames of the clip features, in units of the training std (first second
    skipped: a stream starts standing)."""
    f = clip_style_features(motion)[skip:] / S_std
    return np.concatenate([f.mean(0), f.std(0)])


def evaluate(
    model: LPNModel, out_dir: Path | None = None, frames: int = 240, fine_tune_config: FineTuneConfig = FineTuneConfig()
) -> dict:
    index = build_index([D1])
    S_std = model.p["S_std"]
    source_clip = select(index, style="normal", content="walk")[0]
    source = load_motion(source_clip)
    results: dict[str, object] = {"source": source_clip.name}
    renders = []
    for name in HELD_OUT:
        style = name.removeprefix("d1-")
        clips = select(index, style=style, content=CONTENTS)
        real = [load_motion(c) for c in clips]
        reference = np.mean([motion_stats(m, S_std) for m in real], axis=0)

        def distance(motion: Motion, reference: np.ndarray = reference) -> float:
            return round(float(np.linalg.norm(motion_stats(motion, S_std) - reference) / np.sqrt(reference.size)), 3)

        tuned_name = f"{name}-fine-tuned"
        tuned = fine_tune(model.generator(), real[0], fine_tune_config)
        model.add_style_from_clip(name, real[0])
        model.set_style_film(tuned_name, tuned.film)
        try:
            styled, _ = model.run(source, model.weight_vector({name: 1.0}), frames=frames)
            fine_tuned, _ = model.run(source, model.weight_vector({tuned_name: 1.0}), frames=frames)
        finally:
            model.remove_style(name)
            model.remove_style(tuned_name)
        neutral, _ = model.run(source, model.weight_vector({"normal": 1.0}), frames=frames)
        results[name] = {
            "clip": clips[0].name,
            "distance_new_style": distance(styled),
            "distance_fine_tuned": distance(fine_tuned),
            "distance_normal": distance(neutral),
            "distance_real_normal_walk": distance(source),
            "fine_tune": tuned.summary(),
        }
        renders.append((name, real[0], styled, fine_tuned, neutral))
    if out_dir is not None:
        for name, *motions in renders:
            render_contact_sheet(
                motions,
                Path(out_dir) / f"lpn_heldout_{name}.png",
                frames=6,
                titles=[f"real {name}", f"{name} from clip", f"{name} fine-tuned", "normal"],
            )
    return results


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m tools.lpn_heldout", description=__doc__)
    ap.add_argument("--steps", type=int, help="fine-tune steps (default: FineTuneConfig's)")
    ap.add_argument("--seed", type=int, help="fine-tune seed (default: FineTuneConfig's)")
    ap.add_argument(
        "--no-dropout", dest="dropout", action="store_false", help="fine-tune with the network's dropout off"
    )
    a = ap.parse_args()
    torch.set_num_threads(1)  # as the service's fine-tune job runs
    given = {k: v for k, v in (("steps", a.steps), ("seed", a.seed)) if v is not None}
    cfg = FineTuneConfig(**given, dropout=a.dropout)
    model = load(get_settings().weights_dir / "lpn")
    print(json.dumps(evaluate(model, REPO_ROOT / "out" / "lpn", fine_tune_config=cfg), indent=1))


if __name__ == "__main__":
    main()
