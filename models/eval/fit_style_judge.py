"""`python -m models.eval.fit_style_judge`: fit the sealed evaluation's style judge
(`style_judge.py`) and write its report.

1. **Which labels the datasets share.** A judge fitted on dataset 2's TRAIN clips reads every
   dataset-1 clip; a dataset-1 style is given its dataset-2 namesake (`NAMESAKES`: the two label
   files' words for the same thing) only if at least `AGREEMENT` of its clips read as it. Every
   other dataset-1 style stays a label of its own (`d1-<style>`).
2. **The regularisation** is chosen on VALIDATION clips of both datasets.
3. **The judge** is fitted on the TRAIN clips of both datasets and scored on the held-out
   validation and test clips of each (takes never seen; the data names no performers, so none
   can be held out), and, since dataset 1 has one take per style and content, also by 5-fold
   cross-validation over all its clips.

Writes models/weights/eval/style_judge.npz and docs/eval/style_judge.md (+ .json).
"""

from __future__ import annotations

import argparse
import json
import time
from collections import Counter

import numpy as np

from ..data import build_index, load_motions, select
from ..settings import REPO_ROOT
from .intervals import share, share_table, shown
from .style_judge import StyleJudge, clip_statistics, d1_label, fit_linear, judges_file

D1, D2 = "bandai-namco-1", "bandai-namco-2"
# dataset 1's words for dataset 2's labels (cfg/style_label.txt of each): candidates only
NAMESAKES = {
    "normal": "normal",
    "active": "active",
    "old": "elderly",
    "tired": "exhausted",
    "feminine": "feminine",
    "masculinity": "masculine",
    "childish": "youthful",
}
AGREEMENT = 0.5  # share of a dataset-1 style's clips a dataset-2 judge must read as its namesake
C_GRID = (0.01, 0.03, 0.1, 0.3, 1.0)
FOLDS = 5


def shared_contents(clips) -> set[str]:
    """Contents performed in more than one style: a content only one style has (dataset 1's
    dances, punches, calls in `normal` alone) would teach the judge the content, not the style."""
    styles: dict[str, set[str]] = {}
    for c in clips:
        styles.setdefault(c.content, set()).add(c.style)
    return {k for k, v in styles.items() if len(v) > 1}


def load_clips() -> tuple[list, dict[str, np.ndarray]]:
    index = build_index([D1, D2])
    keep = {d: shared_contents(select(index, dataset=d)) for d in (D1, D2)}
    clips = [c for c in index if c.content in keep[c.dataset]]
    stats = {}
    for lo in range(0, len(clips), 256):
        part = clips[lo : lo + 256]
        for c, m in zip(part, load_motions(part)):
            stats[c.key] = clip_statistics(m)
    return clips, stats


def accuracy(judge: StyleJudge, clips, stats, label) -> tuple[dict, Counter]:
    """Share of clips read as their own label, and the confusion (true, read) counts."""
    read = [judge.labels[int(np.argmax(judge.log_proba(stats[c.key])))] for c in clips]
    truth = [label(c) for c in clips]
    return share(sum(r == t for r, t in zip(read, truth)), len(clips)), Counter(zip(truth, read))


def fit(clips, stats, label, c: float, mapping: dict[str, str]) -> StyleJudge:
    mean, scale, coef, intercept, names = fit_linear([stats[k.key] for k in clips], [label(k) for k in clips], c)
    return StyleJudge(mean, scale, coef, intercept, names, mapping)


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m models.eval.fit_style_judge", description=__doc__)
    ap.parse_args()
    t0 = time.time()
    clips, stats = load_clips()
    d1, d2 = [c for c in clips if c.dataset == D1], [c for c in clips if c.dataset == D2]
    part = lambda cs, split: [c for c in cs if c.split == split]  # noqa: E731

    # 1. label mapping: a dataset-2 judge reads dataset 1
    d2_only = fit(part(d2, "train"), stats, lambda c: c.style, 0.1, {})
    _, confusion = accuracy(d2_only, d1, stats, lambda c: c.style)
    mapping = {}
    for s1, s2 in NAMESAKES.items():
        n = sum(v for (t, _), v in confusion.items() if t == s1)
        if n and confusion[(s1, s2)] / n >= AGREEMENT:
            mapping[s1] = s2
    label = lambda c: c.style if c.dataset == D2 else mapping.get(c.style, d1_label(c.style))  # noqa: E731

    # 2. regularisation on validation
    grid = {}
    for c in C_GRID:
        judge = fit(part(clips, "train"), stats, label, c, mapping)
        grid[c] = [accuracy(judge, part(cs, "val"), stats, label)[0]["share"] for cs in (d1, d2)]
    best = max(C_GRID, key=lambda c: (min(grid[c]), sum(grid[c])))

    # 3. the judge and its held-out scores
    judge = fit(part(clips, "train"), stats, label, best, mapping)
    judge.save(judges_file())
    held = {}
    for name, cs in (("dataset-1", d1), ("dataset-2", d2)):
        for split in ("val", "test"):
            acc, conf = accuracy(judge, part(cs, split), stats, label)
            held[f"{name} {split}"] = {
                "accuracy": acc,
                "misses": {f"{t} -> {r}": v for (t, r), v in conf.items() if t != r},
            }
    rng = np.random.default_rng(0)
    fold = rng.permutation(len(d1)) % FOLDS
    hits = 0
    for k in range(FOLDS):
        train = part(d2, "train") + [c for c, f in zip(d1, fold) if f != k]
        j = fit(train, stats, label, best, mapping)
        acc, _ = accuracy(j, [c for c, f in zip(d1, fold) if f == k], stats, label)
        hits += acc["hits"]
    held["dataset-1 5-fold"] = {"accuracy": share(hits, len(d1)), "misses": {}}
    report = {
        "mapping": mapping,
        "confusion_d1_by_d2_judge": {f"{t} -> {r}": v for (t, r), v in sorted(confusion.items())},
        "c_grid_val": {str(c): v for c, v in grid.items()},
        "c": best,
        "labels": judge.labels,
        "held_out": held,
        "train_clips": {"dataset-1": len(part(d1, "train")), "dataset-2": len(part(d2, "train"))},
        "seconds": round(time.time() - t0, 1),
    }
    out = REPO_ROOT / "docs" / "eval"
    out.mkdir(parents=True, exist_ok=True)
    (out / "style_judge.json").write_text(json.dumps(report, indent=1) + "\n")
    (out / "style_judge.md").write_text(markdown(report, confusion, d1))
    for k, v in held.items():
        print(f"{k:18s} {shown(v['accuracy'])}")
    print(f"mapping {mapping}  C {best}  {report['seconds']} s")


def markdown(r: dict, confusion: Counter, d1) -> str:
    d2_labels = sorted({read for _, read in confusion})
    d1_styles = sorted({c.style for c in d1})
    lines = [
        "# The style judge: held-out accuracy on real clips",
        "",
        "Made by `python -m models.eval.fit_style_judge` (`models/eval/style_judge.py`); "
        f"ran in {r['seconds']:.0f} s. Recipe: mean and standard deviation over 2-s windows of every body joint's "
        "local rotation (6-D, the Hips without heading), its angular speed, the head, hands and feet relative to the "
        "hips in the facing frame and the hips' height and speed; a multinomial logistic regression "
        f"(C = {r['c']}, chosen on validation: "
        + ", ".join(f"{c}: {100 * a[0]:.0f}/{100 * a[1]:.0f} %" for c, a in r["c_grid_val"].items())
        + " on dataset 1 / 2), trained on the TRAIN clips of Bandai Namco datasets 1 and 2 "
        f"({r['train_clips']['dataset-1']} and {r['train_clips']['dataset-2']} clips), every label weighing the "
        "same. Contents only one style performs are left out. The data names no performers, so takes are held "
        "out, not performers.",
        "",
        "## Held-out accuracy (clips read as their own label; 95 % Wilson interval)",
        "",
    ]
    lines += share_table("clips", {k: v["accuracy"] for k, v in r["held_out"].items()})
    lines += [
        "",
        "## Which labels the datasets share",
        "",
        f"A judge fitted on dataset 2's TRAIN clips alone read every dataset-1 clip (rows: the dataset-1 style, "
        f"columns: what it read). A dataset-1 style takes its dataset-2 namesake only if ≥ {AGREEMENT:.0%} of its "
        "clips read as it; the others stay labels of their own (`d1-<style>`).",
        "",
        "| dataset-1 style | namesake | " + " | ".join(d2_labels) + " | mapped |",
        "|---|---|" + "---|" * len(d2_labels) + "---|",
    ]
    for s in d1_styles:
        row = [str(confusion.get((s, lab), 0) or "") for lab in d2_labels]
        mapped = r["mapping"].get(s, "–")
        lines.append(f"| {s} | {NAMESAKES.get(s, '')} | " + " | ".join(row) + f" | {mapped} |")
    lines += ["", "Labels of the judge: " + ", ".join(r["labels"]) + ".", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
