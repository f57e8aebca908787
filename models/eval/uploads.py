"""Styles from one clip, measured on styles the method never trained on (issue 47).

For each dataset-1 style a method ships no style for, one real walk is uploaded as `POST
/v1/styles` does, and neutral walks of both datasets are streamed through it. The move toward
the style is a *coverage* on the style judge's standardised clip statistics:

    coverage(out | in) = 1 - |z(out) - T| / |z(in) - T|,   T = c(in) + mean(z(others)) - c(dataset 1)

c the mean of a dataset's neutral walks, "others" the style's other real walks. A copy of the
upload scores the most one clip can say; where it is clearly closer (>= `CLEAR_COPY`), outputs
must reach `PASS_SHARE` of it. Beside it: a style judge refitted without the upload, and the
least hinge bend against real clips.

    python -m models.eval.uploads [--methods lti,lpn] [--styles proud,giant]   (validation inputs)
"""

from __future__ import annotations

import argparse
import json
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..data import Clip, build_index, load_motions, select
from ..interface import ClipStyles, StreamingModel, UploadedStyles
from ..motion.hinge import Hinges, fit_hinges
from ..motion.rotations import quat_log, swing_twist
from ..motion.skeleton import Motion
from ..motion.twist import bone_axes
from .fit_style_judge import fit, shared_contents
from .run import stylise_toward
from .style_judge import SCALE_FLOOR, StyleJudge, clip_statistics, d1_label, load_style_judge

D1, D2 = "bandai-namco-1", "bandai-namco-2"
HELD_OUT = ("happy", "sad", "angry", "proud", "not-confident", "musical", "giant", "chimpira")
REFERENCE_CONTENTS = ("walk", "walk-left", "walk-right")  # the style's other walking clips
PASS_SHARE, CLEAR_COPY = 0.7, 0.1
FINE_TUNE_STEPS = 300  # the service's default (`lpn_fine_tune_steps`)
JUDGE_PASS = 0.8  # share of a style's outputs its judge must recognise (issue 47)
JUDGE_C = 0.01  # the shipped judge's regularisation, chosen by its cross-validation (docs/eval/style_judge.md)


def judge_clips(index: list[Clip]) -> list[Clip]:
    """Each style's judge's clips: dataset 1's TRAIN and VALIDATION shared contents, dataset 2's walks."""
    d1 = [c for c in select(index, dataset=D1) if c.split in ("train", "val")]
    keep = shared_contents(d1)
    return [c for c in d1 if c.content in keep] + [
        c for c in select(index, dataset=D2, split="train") if c.content == "walk"
    ]


def style_judge_without(
    clips: list[Clip], stats: dict[str, np.ndarray], upload: Clip, mapping: dict[str, str]
) -> StyleJudge:
    """The evaluation's judge, fitted again on `clips` without the uploaded one."""
    label = lambda c: c.style if c.dataset == D2 else mapping.get(c.style, d1_label(c.style))  # noqa: E731
    return fit([c for c in clips if c.key != upload.key], stats, label, JUDGE_C, mapping)


def least_bend(motion: Motion, hinges: Hinges) -> float:
    """The least bend of any hinge joint about its hinge axis, less its real floor (degrees)."""
    axes = bone_axes(motion.skeleton)
    q = motion.rotations / np.linalg.norm(motion.rotations, axis=-1, keepdims=True)
    assert hinges.floor is not None
    return min(
        float(np.degrees((quat_log(swing_twist(q[:, j], axes[j])[0]) @ h).min() - f))
        for j, h, f in zip(hinges.joints, hinges.axes, hinges.floor)
    )


@dataclass
class Ruler:
    """Standardised clip vectors and the neutral centre of each dataset."""

    scale: np.ndarray
    centre: dict[str, np.ndarray]

    def z(self, motion: Motion) -> np.ndarray:
        """The clip's statistics averaged over its windows, standardised: what the coverage compares."""
        return clip_statistics(motion).mean(0) / self.scale

    def coverage(self, out: np.ndarray, start: np.ndarray, dataset: str, target: np.ndarray) -> float:
        """Share of the way from `start` to the style for an output `out` (see the module docstring)."""
        goal = self.centre[dataset] + target
        return float(1.0 - np.linalg.norm(out - goal) / np.linalg.norm(start - goal))


def fit_ruler(index: list[Clip], stats: dict[str, np.ndarray]) -> Ruler:
    """Scale over every real walk the ruler reads; centres from each dataset's neutral walks."""
    d1, d2 = ruler_clips(index)
    vectors = {c.key: stats[c.key].mean(0) for c in d1 + d2}
    scale = np.maximum(np.std(np.stack(list(vectors.values())), axis=0), SCALE_FLOOR)
    centre = {
        ds: np.mean([vectors[c.key] / scale for c in clips if c.style == "normal"], axis=0)
        for ds, clips in ((D1, d1), (D2, d2))
    }
    return Ruler(scale, centre)


def ruler_clips(index: list[Clip]) -> tuple[list[Clip], list[Clip]]:
    """Every real dataset-1 walk (`REFERENCE_CONTENTS`) and dataset-2 TRAIN walk."""
    d1 = [c for c in select(index, dataset=D1) if c.content in REFERENCE_CONTENTS]
    return d1, [c for c in select(index, dataset=D2, split="train") if c.content == "walk"]


def real_statistics(index: list[Clip]) -> tuple[dict[str, np.ndarray], Hinges]:
    """`clip_statistics` of every clip the ruler and judges read (each once), and the hinges."""
    d1, d2 = ruler_clips(index)
    clips = list({c.key: c for c in d1 + d2 + judge_clips(index)}.values())
    motions = load_motions(clips)
    stats = {c.key: clip_statistics(m) for c, m in zip(clips, motions)}
    walks = {c.key for c in d1 + d2}
    rotations = np.concatenate([m.rotations for c, m in zip(clips, motions) if c.key in walks])
    return stats, fit_hinges(motions[0].skeleton, rotations)


def held_out_styles(model: StreamingModel, styles: tuple[str, ...]) -> list[str]:
    """The styles of `styles` the model was not trained on: it ships no style by that name."""
    shipped = set(model.styles())
    return [s for s in styles if s not in shipped and f"d1-{s}" not in shipped]


def upload_variants(model: StreamingModel, clip: Motion) -> dict[str, StreamingModel]:
    """The model with the clip's style installed as `upload`: `tuned`, and `instant` where it can."""
    out: dict[str, StreamingModel] = {}
    if not isinstance(model, UploadedStyles):
        return out
    if isinstance(model, ClipStyles):
        instant = model.with_own_styles()
        instant.install_style("upload", instant.style_from_clip(clip))
        out["instant"] = instant
    tuned = model.with_own_styles()
    job = tuned.fine_tune_style("upload", clip, lambda fraction, message: None, FINE_TUNE_STEPS)
    if job.style is not None:
        tuned.install_style("upload", job.style)
        out["tuned"] = tuned
    elif "instant" in out:  # tuning kept the clip's own style
        out["tuned"] = out["instant"]
    return out


def neutral_inputs(index: list[Clip], split: str) -> dict[str, list[Motion]]:
    """Neutral straight walks: dataset 2's of `split`, and every dataset-1 one."""
    d2 = [c for c in select(index, dataset=D2, split=split, style="normal") if c.content == "walk"]
    d1 = [c for c in select(index, dataset=D1, style="normal") if c.content == "walk"]
    return {D2: load_motions(d2), D1: load_motions(d1)}


def evaluate(models: dict[str, StreamingModel], split: str, styles: tuple[str, ...] = HELD_OUT) -> list[dict]:
    index = build_index([D1, D2])
    stats, hinges = real_statistics(index)
    ruler = fit_ruler(index, stats)
    inputs = neutral_inputs(index, split)
    starts = {ds: [ruler.z(m) for m in motions] for ds, motions in inputs.items()}  # each input read once
    fitted_on, mapping = judge_clips(index), load_style_judge().mapping
    rows: list[dict] = []
    for style in styles:
        walks = [c for c in select(index, dataset=D1, style=style) if c.content in REFERENCE_CONTENTS]
        upload = next(c for c in sorted(walks, key=lambda c: c.name) if c.content == "walk")
        reference = [c for c in walks if c.name != upload.name]
        clip, *others = load_motions([upload, *reference])
        target = np.mean([ruler.z(m) for m in others], axis=0) - ruler.centre[D1]
        z_clip = ruler.z(clip)
        copy = {ds: float(np.mean([ruler.coverage(z_clip, n, ds, target) for n in starts[ds]])) for ds in starts}
        judge, wanted = style_judge_without(fitted_on, stats, upload, mapping), mapping.get(style, d1_label(style))
        copy_read = judge.read_own(stats[upload.key], D1, upload.content)
        for method, model in models.items():
            if style not in held_out_styles(model, styles):
                continue
            t0 = time.perf_counter()
            variants = upload_variants(model, clip)
            seconds = time.perf_counter() - t0
            if not variants:
                rows.append({"style": style, "method": method, "variant": "refused", "copy": copy})
                continue
            for variant, styled in variants.items():
                outs = {ds: stylise_toward(styled, motions, ["upload"])["upload"] for ds, motions in inputs.items()}
                cov = {
                    ds: [ruler.coverage(ruler.z(o), n, ds, target) for o, n in zip(outs[ds], starts[ds])] for ds in outs
                }
                reads = {ds: [judge.read_own(clip_statistics(o), ds, "walk") for o in outs[ds]] for ds in outs}
                judged = float(np.mean([r == wanted for ds in reads for r in reads[ds]]))
                share = {ds: float(np.mean(v)) / copy[ds] if copy[ds] > 0 else float("nan") for ds, v in cov.items()}
                rows.append(
                    {
                        "style": style,
                        "method": method,
                        "variant": variant,
                        "copy": copy,
                        "coverage": {ds: float(np.mean(v)) for ds, v in cov.items()},
                        "clips": {ds: len(v) for ds, v in cov.items()},
                        "share_of_copy": share,
                        "passes": passes(share, copy),
                        "make_seconds": round(seconds, 1),
                        "judged": judged,
                        "judged_by_source": {ds: float(np.mean([r == wanted for r in v])) for ds, v in reads.items()},
                        "judge_reads": {ds: dict(Counter(v).most_common()) for ds, v in reads.items()},
                        "judge_passes": bool(judged >= JUDGE_PASS),
                        "copy_judged": copy_read == wanted,
                        "least_bend": min(least_bend(o, hinges) for ds in outs for o in outs[ds]),
                    }
                )
    return rows


def passes(share: dict[str, float], copy: dict[str, float]) -> bool | None:
    """Whether outputs reach PASS_SHARE of the copy wherever it is clearly closer; None: nowhere."""
    scored = [ds for ds in share if copy[ds] >= CLEAR_COPY]
    return all(share[ds] >= PASS_SHARE for ds in scored) if scored else None


def verdict(row: dict) -> str:
    """yes / no, or why the row cannot be scored."""
    if row["passes"] is None:
        return "– (the clip itself is not closer)"
    return "yes" if row["passes"] else "no"


def _per_source(values: dict[str, float], copy: dict[str, float], fmt: str) -> str:
    """'D2 / D1' values, a dataset where the copy is not clearly closer in brackets (not scored)."""
    cell = lambda ds: fmt.format(values[ds]) if copy[ds] >= CLEAR_COPY else f"({fmt.format(values[ds])})"  # noqa: E731
    return f"{cell(D2)} / {cell(D1)}"


def table(rows: list[dict]) -> list[str]:
    lines = [
        "| method | way | style | copy (D2 / D1) | coverage D2 | coverage D1 | share of copy (D2 / D1) | passes "
        "| judge read (D2 / D1) | judge passes | copy read | least bend (°) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        copy = f"{r['copy'][D2]:.2f} / {r['copy'][D1]:.2f}"
        if r["variant"] == "refused":
            lines.append(f"| {r['method']} | refused | {r['style']} | {copy} | | | | no | | no | | |")
            continue
        c = r["coverage"]
        lines.append(
            f"| {r['method']} | {r['variant']} | {r['style']} | {copy} | {c[D2]:.2f} ({r['clips'][D2]}) "
            f"| {c[D1]:.2f} ({r['clips'][D1]}) | {_per_source(r['share_of_copy'], r['copy'], '{:.0%}')} "
            f"| {verdict(r)} | {r['judged']:.0%} "
            f"({r['judged_by_source'][D2]:.0%} / {r['judged_by_source'][D1]:.0%}) "
            f"| {'yes' if r['judge_passes'] else 'no'} | {'yes' if r['copy_judged'] else 'no'} | {r['least_bend']:+.1f} |"
        )
    return lines


def main() -> None:
    from ..registry import load_models
    from ..settings import get_settings

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--final", action="store_true", help="dataset-2 TEST inputs (what `make eval-final` scores)")
    parser.add_argument("--methods", default="lti,erd,lpn")
    parser.add_argument("--styles", default=",".join(HELD_OUT))
    parser.add_argument("--out", type=Path, help="also write the rows as JSON here")
    args = parser.parse_args()
    methods = args.methods.split(",")
    models = {k: v for k, v in load_models(get_settings().weights_dir).items() if k in methods}
    rows = evaluate(models, "test" if args.final else "val", tuple(args.styles.split(",")))
    print("\n".join(table(rows)))
    if args.out:
        args.out.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
