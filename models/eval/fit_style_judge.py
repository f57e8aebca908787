"""`python -m models.eval.fit_style_judge`: fit the sealed evaluation's style judge and report.

1. A dataset-1 style takes its dataset-2 namesake's label only if at least `AGREEMENT` of its
   clips read as it under a dataset-2 judge; others stay labels of their own (read as `other`).
2. The regularisation is chosen by 5-fold cross-validation over dataset 1, one style and
   content held out together.
3. The judge is fitted on both datasets' TRAIN clips and scored on held-out clips.

The test split is never loaded here. Writes models/weights/eval/style_judge.npz and
docs/eval/style_judge.md (+ .json).
"""

from __future__ import annotations

import argparse
import json
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..data import Clip, build_index, load_motions, select
from ..settings import REPO_ROOT
from .intervals import share, shown
from .style_judge import OTHER, StyleJudge, centres_of, clip_statistics, d1_label, fit_linear, judges_file

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
C_GRID = (0.003, 0.01, 0.03, 0.1, 0.3)
FOLDS = 5
REPEATS = 5  # fold draws: with ten clips a style one draw moves the score by several clips
TEMPLATE = Path(__file__).with_name("templates") / "style_judge.md"  # the report's fixed prose


def shared_contents(clips: list[Clip]) -> set[str]:
    """Contents performed in more than one style: one style's content would teach the content."""
    styles: dict[str, set[str]] = {}
    for c in clips:
        styles.setdefault(c.content, set()).add(c.style)
    return {k for k, v in styles.items() if len(v) > 1}


def folds(clips: list[Clip], draw: int) -> np.ndarray:
    """Each clip's fold in draw `draw`: every take of one style and content in the same fold."""
    groups = sorted({(c.style, c.content) for c in clips})
    fold = dict(zip(groups, np.random.default_rng(draw).permutation(len(groups)) % FOLDS))
    return np.array([fold[(c.style, c.content)] for c in clips])


def load_clips() -> tuple[list[Clip], dict[str, np.ndarray]]:
    index = [c for c in build_index([D1, D2]) if c.split != "test"]
    keep = {d: shared_contents(select(index, dataset=d)) for d in (D1, D2)}
    clips = [c for c in index if c.content in keep[c.dataset]]
    stats = {}
    for lo in range(0, len(clips), 256):
        part = clips[lo : lo + 256]
        for c, m in zip(part, load_motions(part)):
            stats[c.key] = clip_statistics(m)
    return clips, stats


def fit(
    clips: list[Clip],
    stats: dict[str, np.ndarray],
    label: Callable[[Clip], str],
    c: float,
    mapping: dict[str, str],
    centred_on: list[Clip] | None = None,
) -> StyleJudge:
    """A judge fitted on `clips`, its centres taken from `centred_on` (default: the same clips)."""
    ref = clips if centred_on is None else centred_on
    centres = centres_of(
        [stats[k.key] for k in ref], [k.dataset for k in ref], [k.content for k in ref], [k.style for k in ref]
    )
    x = [stats[k.key] - centres[f"{k.dataset}/{k.content}"] for k in clips]
    mean, scale, coef, intercept, names = fit_linear(x, [label(k) for k in clips], [k.dataset for k in clips], c)
    return StyleJudge(mean, scale, coef, intercept, names, mapping, centres)


def scores(reads: list[tuple[str, str, str, str]]) -> dict:
    """Accuracy of (truth, read, own truth, own read): named-or-`other` and strict."""
    return {
        "accuracy": share(sum(t == r for t, r, _, _ in reads), len(reads)),
        "own_labels": share(sum(t == r for _, _, t, r in reads), len(reads)),
        "misses": dict(Counter(f"{t} -> {r}" for t, r, _, _ in reads if t != r).most_common()),
    }


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m models.eval.fit_style_judge", description=__doc__)
    ap.parse_args()
    t0 = time.time()
    clips, stats = load_clips()
    d1, d2 = [c for c in clips if c.dataset == D1], [c for c in clips if c.dataset == D2]
    part = lambda cs, *splits: [c for c in cs if c.split in splits]  # noqa: E731
    seen = part(d1, "train", "val")  # the test split chooses nothing

    # 1. label mapping: a dataset-2 judge reads dataset 1
    d2_only = fit(part(d2, "train"), stats, lambda c: c.style, 0.1, {}, part(d2, "train") + seen)
    confusion = Counter((c.style, d2_only.read_own(stats[c.key], c.dataset, c.content)) for c in seen)
    mapping = {}
    for s1, s2 in NAMESAKES.items():
        n = sum(v for (t, _), v in confusion.items() if t == s1)
        if n and confusion[(s1, s2)] / n >= AGREEMENT:
            mapping[s1] = s2
    label = lambda c: c.style if c.dataset == D2 else mapping.get(c.style, d1_label(c.style))  # noqa: E731
    truth = lambda c: c.style if c.dataset == D2 else mapping.get(c.style, OTHER)  # noqa: E731

    def reads(judge: StyleJudge, cs: list[Clip]) -> list[tuple[str, str, str, str]]:
        return [
            (
                truth(c),
                judge.read(stats[c.key], c.dataset, c.content),
                label(c),
                judge.read_own(stats[c.key], c.dataset, c.content),
            )
            for c in cs
        ]

    # 2. regularisation by cross-validation over dataset 1, repeated over fold draws (few clips a style)
    grid: dict[float, list[int]] = {}
    oof: dict[float, list[dict]] = {}
    for c in C_GRID:
        oof[c] = []
        for rep in range(REPEATS):
            fold = folds(seen, rep)
            got: dict[str, tuple] = {}
            for k in range(FOLDS):
                j = fit(part(d2, "train") + [x for x, f in zip(seen, fold) if f != k], stats, label, c, mapping)
                kept_out = [x for x, f in zip(seen, fold) if f == k]
                got.update({x.key: r for x, r in zip(kept_out, reads(j, kept_out))})
            oof[c].append(got)
        grid[c] = [scores(list(g.values()))["accuracy"]["hits"] for g in oof[c]]
        print(f"C {c}: dataset-1 cross-validation hits {grid[c]} of {len(seen)}", flush=True)
    best = max(C_GRID, key=lambda c: (sum(grid[c]), -abs(np.log(c / 0.1))))

    # 3. the judge and its held-out scores
    judge = fit(part(clips, "train"), stats, label, best, mapping)
    judge.save(judges_file())
    draws = [scores([g[c.key] for c in seen]) for g in oof[best]]
    d2_val = reads(judge, part(d2, "val"))
    held = {
        "dataset-2 val": scores(d2_val),
        "dataset-1 val": scores(reads(judge, part(d1, "val"))),
        "dataset-1 cross-validation": draws[0],
    }
    cv_rows = [(c, g[c.key]) for g in oof[best] for c in seen]
    report = {
        "mapping": mapping,
        "confusion_d1_by_d2_judge": {f"{t} -> {r}": v for (t, r), v in sorted(confusion.items())},
        "c_grid_cv": {str(c): v for c, v in grid.items()},
        "cv_clips": len(seen),
        "c": best,
        "labels": judge.labels,
        "held_out": held,
        "d1_cv_draws": [d["accuracy"] for d in draws],
        "d1_cv_by_style": _by(cv_rows, lambda c: c.style),
        "d1_cv_by_content": _by(cv_rows, lambda c: c.content),
        "d2_val_by_style": _by(list(zip(part(d2, "val"), d2_val)), lambda c: c.style),
        "train_clips": {"dataset-1": len(part(d1, "train")), "dataset-2": len(part(d2, "train"))},
        "seconds": round(time.time() - t0, 1),
    }
    out = REPO_ROOT / "docs" / "eval"
    out.mkdir(parents=True, exist_ok=True)
    (out / "style_judge.json").write_text(json.dumps(report, indent=1) + "\n")
    (out / "style_judge.md").write_text(markdown(report, confusion, d1))
    for name, v in held.items():
        print(f"{name:28s} {shown(v['accuracy'])}  own labels {shown(v['own_labels'])}")
    print(f"mapping {mapping}  C {best}  {report['seconds']} s; the rest in {out / 'style_judge.md'}")


def _by(rows: list, key: Callable[[Clip], str]) -> dict[str, dict]:
    """Reads grouped by `key`: how many, how many right, and what they read as."""
    out: dict[str, dict] = {}
    for c, (t, r, _, own) in rows:
        g = out.setdefault(key(c), {"truth": t, "clips": 0, "hits": 0, "read": Counter(), "read_own": Counter()})
        g["clips"] += 1
        g["hits"] += t == r
        g["read"][r] += 1
        g["read_own"][own] += 1
    return {k: {**v, "read": dict(v["read"]), "read_own": dict(v["read_own"])} for k, v in sorted(out.items())}


def markdown(r: dict, confusion: Counter, d1: list[Clip]) -> str:
    d2_labels = sorted({read for _, read in confusion})
    d1_styles = sorted({c.style for c in d1})
    lines = [
        "# The style judge: held-out accuracy on real clips",
        "",
        TEMPLATE.read_text()
        .format(
            seconds=r["seconds"],
            train_d1=r["train_clips"]["dataset-1"],
            train_d2=r["train_clips"]["dataset-2"],
            c=r["c"],
            repeats=REPEATS,
            grid="; ".join(f"{c}: {'/'.join(map(str, h))} of {r['cv_clips']}" for c, h in r["c_grid_cv"].items()),
        )
        .rstrip("\n"),
        "",
        "| clips | accuracy | own labels |",
        "|---|---|---|",
    ]
    for k, v in r["held_out"].items():
        lines.append(f"| {k} | {shown(v['accuracy'])} | {shown(v['own_labels'])} |")
    lines += [
        "",
        "*dataset-1 cross-validation*: each of dataset 1's TRAIN and VALIDATION clips read by a judge fitted "
        f"without it (5 folds, the takes of one style and content together, with dataset 2's TRAIN clips), at the chosen C, first of {len(r['d1_cv_draws'])} "
        "fold draws. Every draw: "
        + "; ".join(shown(d) for d in r["d1_cv_draws"])
        + f"; mean {100 * sum(d['share'] for d in r['d1_cv_draws']) / len(r['d1_cv_draws']):.1f} %. The test split "
        "is not loaded by the fit: `make eval-final` reads it once.",
        "",
        "Misses (truth -> read): "
        + "; ".join(
            f"{k}: " + ", ".join(f"{m} ({n})" for m, n in v["misses"].items())
            for k, v in r["held_out"].items()
            if v["misses"]
        )
        + ".",
        "",
        "## Dataset 1, cross-validation reads per style and per content",
        "",
        f"Every fold draw's reads together: each clip is read {len(r['d1_cv_draws'])} times.",
        "",
        "| dataset-1 style | truth | reads | right | read as | own-label read |",
        "|---|---|---|---|---|---|",
    ]
    for s, v in r["d1_cv_by_style"].items():
        lines.append(
            f"| {s} | {v['truth']} | {v['clips']} | {v['hits']} | {_counts(v['read'])} | {_counts(v['read_own'])} |"
        )
    lines += ["", "| content | reads | right |", "|---|---|---|"]
    for s, v in r["d1_cv_by_content"].items():
        lines.append(f"| {s} | {v['clips']} | {v['hits']} |")
    lines += [
        "",
        "## Dataset 2, validation reads per style",
        "",
        "| style | clips | right | read as |",
        "|---|---|---|---|",
    ]
    for s, v in r["d2_val_by_style"].items():
        lines.append(f"| {s} | {v['clips']} | {v['hits']} | {_counts(v['read'])} |")
    lines += [
        "",
        "## Which labels the datasets share",
        "",
        "A judge fitted on dataset 2's TRAIN clips alone read every dataset-1 TRAIN and VALIDATION clip (rows: "
        f"the dataset-1 style, columns: what it read). A dataset-1 style takes its dataset-2 namesake only if ≥ "
        f"{AGREEMENT:.0%} of its clips read as it; the others stay labels of their own (`d1-<style>`).",
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


def _counts(c: dict[str, int]) -> str:
    return ", ".join(f"{k} {n}" for k, n in sorted(c.items(), key=lambda kv: -kv[1]))


if __name__ == "__main__":
    main()
