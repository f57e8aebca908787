"""The sealed evaluation: every method, its published core alone, the input unchanged and real
clips, on every source, fresh and running, by judges and physical metrics no model enforces.

`make eval` scores the VALIDATION inputs (every choice is made there); `make eval-final` scores
the sealed test inputs once, writes docs/evaluation.md and logs the run in
docs/eval/final_runs.md. Models are reached only through the streaming interface.
"""

from __future__ import annotations

import datetime as dt
import json
import platform
import subprocess
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from ..data import Clip, build_index, load_motions, select
from ..interface import StreamingModel
from ..motion.novelty import FADED
from ..motion.skeleton import Motion
from ..registry import load_models
from ..settings import REPO_ROOT, get_settings
from . import uploads
from .features import clip_features
from .intervals import share, share_table, shown
from .judges import load_judges
from .metrics import SKID_SPEED
from .physical import ClipPhysics, Input, Reference, measure, summarise
from .run import HISTORY_FRAMES, run_after_history, stylise_toward
from .sources import D2, Source, input_sources
from .style_judge import load_style_judge

# gates (the model issue's), per source x method x style, fresh and running
GATE_PLAUSIBLE = 0.95  # share of clips plausible on every joint
GATE_POPS = 2.0  # pops at most this times real clips'
GATE_JITTER = 1.5  # p90 over clips of the jitter ratio
GATE_SLIDE = 2.0  # each content's planted-foot p95 at most this times the real style's or the input's
GATE_STYLE = {D2: 0.90}  # style read right on the new judge; other sources:
GATE_STYLE_OTHER = 0.75
GATE_CONTENT = 0.90  # dataset 2 only: the content judge knows its ten contents
FINAL_RUNS = "docs/eval/final_runs.md"
# the report's fixed prose, its braces filled in by `markdown`
REPORT, UPLOADS_REPORT = (Path(__file__).with_name("templates") / name for name in ("evaluation.md", "uploads.md"))


class Judges(NamedTuple):
    """What scores a row: the style judge, the older style and content judges, the real reference."""

    style: Any  # style_judge.StyleJudge
    old: Any  # judges.Judges
    ref: Reference


def evaluate(
    final: bool = False, quick: bool = False, methods: tuple[str, ...] | None = None, out: Path | None = None
) -> dict:
    """Score everything; write the report (docs/ for a final run, else out/)."""
    torch.set_num_threads(1)
    t0 = time.time()
    split = "test" if final else "val"
    out = (
        Path(out)
        if out is not None
        else REPO_ROOT / ("docs" if final else "out/eval-quick" if quick else "out/eval-val")
    )
    judge, old = load_style_judge(), load_judges()
    full, variants = _variants(methods)
    index = build_index([D2])
    d2_styles = {c.style for c in index}  # the styles scored: every method's, with dataset-2 clips
    styles = [
        s for s in judge.labels if all(s in m.styles() for m in full.values()) and s != "normal" and s in d2_styles
    ]
    if quick:
        styles = styles[:2]
    ref, real, real_contents = real_clips(index, styles, final, quick)
    judges = Judges(judge, old, ref)
    sources = input_sources(split, quick=quick)
    rows = [_row("real", None, "fresh", s, real[s], None, real_contents[s], judges) for s in styles]
    for source in sources:
        rows += _source_rows(source, variants, styles, judges)
    for r in rows:
        r["gates"] = gates(r, rows)
    results = {
        "rows": rows,
        # styles from one clip, held out of each method's training (issue 47); not in the quick run
        "uploads": [] if quick else uploads.evaluate(full, split),
        "meta": {
            "split": split,
            "final": final,
            "quick": quick,
            "styles": styles,
            "sources": {src.label: {"clips": src.names} for src in sources},
            "skate_limit_cm_s": ref.skate_limit,
            "history_frames": HISTORY_FRAMES,
            "judge": json.loads((REPO_ROOT / "docs/eval/style_judge.json").read_text())["held_out"],
            "commit": _commit(),
            "date": dt.date.today().isoformat(),
            "seconds": round(time.time() - t0, 1),
            "machine": f"{platform.machine()} CPU, torch threads=1",
        },
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / "eval").mkdir(exist_ok=True)
    (out / "eval" / "results.json").write_text(json.dumps(results, indent=1, default=float) + "\n")
    if final and not quick:
        _append_final_run(results)
    (out / "evaluation.md").write_text(markdown(results))
    return results


def _variants(
    methods: tuple[str, ...] | None,
) -> tuple[dict[str, StreamingModel], dict[str, StreamingModel | None]]:
    """(the methods, the variants scored: None (the input), then each method and its core)."""
    weights = get_settings().weights_dir
    full = load_models(weights)
    core = load_models(weights, core_only=True)
    if methods is not None:
        full, core = {k: v for k, v in full.items() if k in methods}, {k: v for k, v in core.items() if k in methods}
    variants: dict[str, StreamingModel | None] = {"identity": None}
    for name in full:
        variants[name], variants[f"{name} core"] = full[name], core[name]
    return full, variants


def real_clips(index: list[Clip], styles: list[str], final: bool, quick: bool) -> tuple[Reference, dict, dict]:
    """(reference, real clips per style, contents); radii and limits from VALIDATION (final: test)."""
    split = "test" if final else "val"
    val = {s: load_motions(select(index, split="val", style=s)) for s in styles}
    train = {s: load_motions(select(index, split="train", style=s)) for s in styles}
    val_contents = {s: [c.content for c in select(index, split="val", style=s)] for s in styles}
    halve = (lambda v: v) if final else (lambda v: v[0::2])  # noqa: E731
    train_contents = {s: [c.content for c in select(index, split="train", style=s)] for s in styles}
    ref = Reference.fit(
        train, {s: halve(v) for s, v in val.items()}, train_contents, {s: halve(v) for s, v in val_contents.items()}
    )
    if final:
        real = {s: load_motions(select(index, split="test", style=s)) for s in styles}
    else:
        real = {s: v[1::2] for s, v in val.items()}
    if quick:
        real = {s: v[:4] for s, v in real.items()}
    # what each real clip performs: the style judge reads a clip against its session's content
    contents = {s: [c.content for c in select(index, split=split, style=s)] for s in styles}
    if not final:
        contents = {s: v[1::2] for s, v in contents.items()}
    return ref, real, {s: v[: len(real[s])] for s, v in contents.items()}


def _source_rows(
    source: Source, variants: dict[str, StreamingModel | None], styles: list[str], judges: Judges
) -> list[dict]:
    """Every variant's rows on one source: fresh sessions, then (for a model) running ones."""
    rows = []
    measured = [Input.of(m, judges.ref) for m in source.motions]
    for variant, model in variants.items():
        fades: dict[str, list[np.ndarray]] = {}
        fresh = stylise_toward(model, source.motions, styles, fades)
        for s in styles:
            row = _row(variant, source, "fresh", s, fresh[s], measured, source.contents, judges)
            rows.append({**row, "faded": faded_share(fades[s])})
        if model is None:
            continue
        placed, running = run_after_history(model, source.motions, styles, fades)
        placed_measured = [Input.of(m, judges.ref) for m in placed]
        for s in styles:
            row = _row(variant, source, "running", s, running[s], placed_measured, source.contents, judges)
            rows.append({**row, "faded": faded_share(fades[s])})
    return rows


def _row(
    variant: str,
    source: Source | None,
    session: str,
    style: str,
    outs: list[Motion],
    inputs: list[Input] | None,
    contents: list[str],
    judges: Judges,
) -> dict:
    """One row: a variant's outputs toward `style` from one source's inputs (None: real clips)."""
    ref = judges.ref
    read = judges.style.predict(outs, D2 if source is None else source.dataset, contents)
    phys: list[ClipPhysics] = [
        measure(ref, style, o, None if inputs is None else inputs[i], contents[i]) for i, o in enumerate(outs)
    ]
    row = {
        "variant": variant,
        "source": "real" if source is None else source.label,
        "dataset": D2 if source is None else source.dataset,
        "session": session,
        "style": style,
        "clips": len(outs),
        "style_acc": share(sum(r == style for r in read), len(read)),
        "read_as": {k: read.count(k) for k in sorted(set(read))},
        "plausible": share(sum(p.plausible for p in phys), len(phys)),
        **summarise(phys, ref, contents, style),
    }
    if source is not None and source.dataset == D2:
        feats = [clip_features(m) for m in outs]
        got = judges.old.predict_content(feats)
        row["content_acc"] = share(sum(g == c for g, c in zip(got, contents)), len(got))
        row["style_acc_old"] = share(sum(p == style for p in judges.old.predict_style(feats)), len(feats))
    return row


def faded_share(fades: list[np.ndarray]) -> dict:
    """The share of frames faded past `novelty.FADED`, with its 95 % interval."""
    return share(int(sum(int(np.sum(f > FADED)) for f in fades)), int(sum(len(f) for f in fades)))


def gates(row: dict, rows: list[dict]) -> dict:
    """The model gates on one row (none on identity and real rows), each with its value."""
    if row["variant"] in ("identity", "real"):
        return {}
    real = next(r for r in rows if r["variant"] == "real" and r["style"] == row["style"])
    need = GATE_STYLE.get(row["dataset"], GATE_STYLE_OTHER)
    checks = {
        "plausible": row["plausible"]["share"] >= GATE_PLAUSIBLE,
        "pops": row["pops"] <= GATE_POPS * max(real["pops"], 1e-3),
        "jitter": row["jitter_p90"] <= GATE_JITTER,
        "slide": row["slide_ratio"] <= GATE_SLIDE,
        "style": row["style_acc"]["share"] >= need,
    }
    if "content_acc" in row:
        checks["content"] = row["content_acc"]["share"] >= GATE_CONTENT
    return {**checks, "all": all(checks.values())}


def _commit() -> str:
    try:
        return subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=REPO_ROOT, capture_output=True, text=True, check=True
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def final_runs() -> list[str]:
    """The lines of docs/eval/final_runs.md that record a run."""
    path = REPO_ROOT / FINAL_RUNS
    return [ln for ln in path.read_text().splitlines() if ln.startswith("| 20")] if path.exists() else []


def _append_final_run(r: dict) -> None:
    path = REPO_ROOT / FINAL_RUNS
    if not path.exists():
        path.write_text(
            "# Final runs: each time the sealed test inputs were scored\n\n"
            "`make eval-final` appends a line; it is run once a change is finished, never to choose between "
            "changes (docs/evaluation.md).\n\n| date | commit | summary |\n|---|---|---|\n"
        )
    with path.open("a") as f:
        f.write(f"| {r['meta']['date']} | {r['meta']['commit']} | {_summary(r)} |\n")


def _summary(r: dict) -> str:
    scored = [x for x in r["rows"] if x["gates"]]
    by: dict = {}
    for x in scored:
        key = (x["variant"], x["session"])
        passed, total = by.get(key, (0, 0))
        by[key] = (passed + x["gates"]["all"], total + 1)
    return "; ".join(f"{v} {s}: {p}/{n} rows pass" for (v, s), (p, n) in by.items())


# ---------------------------------------------------------------- the report


def _pct(x: float) -> str:
    return "–" if x != x else f"{100 * x:.0f}%"


def _cell(row: dict, key: str) -> str:
    mark = "" if key not in row["gates"] else ("✅ " if row["gates"][key] else "❌ ")
    value = {
        "style": lambda: shown(row["style_acc"]),
        "content": lambda: shown(row["content_acc"]) if "content_acc" in row else "–",
        "plausible": lambda: f"{shown(row['plausible'])}; worst {row['worst_joint']} {_pct(row['worst_within'])}",
        "pops": lambda: f"{100 * row['pops']:.1f}% ({row['pops_joint']})",
        "jitter": lambda: (
            "–" if row["jitter_p90"] != row["jitter_p90"] else f"{row['jitter_median']:.2f} / {row['jitter_p90']:.2f}"
        ),
        "slide": lambda: f"{row['slide_ratio']:.1f}× ({row['slide_content'] or '–'}); {row['slide_p95']:.0f}",
    }[key]()
    return mark + value


def markdown(r: dict) -> str:
    meta = r["meta"]
    final = meta["final"]
    runs = final_runs()
    fixed = REPORT.read_text().format(
        history_s=meta["history_frames"] // 30,
        judge_table="\n".join(share_table("real clips", {k: v["accuracy"] for k, v in meta["judge"].items()})),
        gate_style_other=GATE_STYLE_OTHER,
        gate_content=GATE_CONTENT,
        gate_jitter=GATE_JITTER,
        gate_slide=GATE_SLIDE,
        skate_limit=meta["skate_limit_cm_s"],
        skid_speed=SKID_SPEED,
        faded=FADED,
    )
    lines = [
        "# Evaluation" + ("" if final else " on the VALIDATION inputs (where choices are made)"),
        "",
        f"Command: `{'make eval-final' if final else 'make eval'}` (`python -m models.eval"
        f"{' --final' if final else ''}`), commit {meta['commit']}, {meta['date']}; ran in {meta['seconds']:.0f} s "
        f"on {meta['machine']}. Raw numbers: [`eval/results.json`](eval/results.json). "
        + (f"**Final runs so far: {len(runs)}** ([list](eval/final_runs.md))." if final else ""),
        "",
        fixed.rstrip("\n"),
        "",
    ]
    lines += _per_source(
        r,
        "## Rows passing every gate (of the styles), per source",
        ("fresh", "running"),
        lambda rows: f"{sum(x['gates']['all'] for x in rows)} of {len(rows)}",
    )
    lines += _fade_summary(r)
    for source in ["real", *meta["sources"]]:
        lines += _source_table(r, source)
    lines += _uploads_section(r.get("uploads", []))
    lines += [
        "## Renders",
        "",
        "Oriented contact sheets of a CMU, a Xia and a dataset-1 input through every method and core "
        "(`python -m tools.renders`): [docs/eval/renders/](eval/renders/).",
        "",
    ]
    return "\n".join(lines) + "\n"


def _per_source(r: dict, title: str, sessions: tuple[str, ...], cell: Callable[[list[dict]], str]) -> list[str]:
    """A variant x source table of `cell(rows)`, a column per session when there are several."""
    sources = list(r["meta"]["sources"])
    variants = list(dict.fromkeys(x["variant"] for x in r["rows"] if x["gates"]))
    by = "session | " if len(sessions) > 1 else ""
    lines = [title, "", f"| variant | {by}" + " | ".join(sources) + " |", "|---|" + "---|" * (len(sources) + bool(by))]
    for v in variants:
        for session in sessions:
            cells = []
            for src in sources:
                rows = [x for x in r["rows"] if (x["variant"], x["source"], x["session"]) == (v, src, session)]
                cells.append(cell(rows) if rows else "–")
            lines.append(f"| {v} | " + (f"{session} | " if by else "") + " | ".join(cells) + " |")
    return lines + [""]


def _uploads_section(rows: list[dict]) -> list[str]:
    if not rows:
        return []
    return [
        UPLOADS_REPORT.read_text()
        .format(pass_share=uploads.PASS_SHARE, clear_copy=uploads.CLEAR_COPY, judge_pass=uploads.JUDGE_PASS)
        .rstrip("\n"),
        "",
        *uploads.table(rows),
        "",
    ]


def _fade_summary(r: dict) -> list[str]:
    """Frames faded per variant and source, fresh sessions, over every style."""

    def share(rows: list[dict]) -> str:
        hits, n = sum(x["faded"]["hits"] for x in rows), sum(x["faded"]["n"] for x in rows)
        return f"{100 * hits / n:.1f}%" if n else "–"

    return _per_source(
        r, "## Frames faded toward the input, per source (fresh sessions, every style)", ("fresh",), share
    )


def _source_table(r: dict, source: str) -> list[str]:
    rows = [x for x in r["rows"] if x["source"] == source]
    clips = rows[0]["clips"] if rows else 0
    title = "Real clips of each style" if source == "real" else f"Source: {source} ({clips} clips)"
    lines = [
        f"## {title}",
        "",
        "| variant | session | style | style read | content | plausible clips | pops | jitter | slide | skate | "
        "skid | path | drift cm | faded | read as |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for x in rows:
        top = ", ".join(f"{k} {n}" for k, n in sorted(x["read_as"].items(), key=lambda kv: -kv[1])[:3])
        path = (
            f"{x['path_ratio_median']:.2f} ({x['path_ratio_worst']:.2f})"
            if x["path_ratio_median"] == x["path_ratio_median"]
            else "–"
        )
        drift = f"{x['end_drift_median']:.0f}" if x["end_drift_median"] == x["end_drift_median"] else "–"
        faded = f"{100 * x['faded']['share']:.1f}%" if "faded" in x else "–"
        lines.append(
            f"| {x['variant']} | {x['session']} | {x['style']} | {_cell(x, 'style')} | {_cell(x, 'content')} | "
            f"{_cell(x, 'plausible')} | {_cell(x, 'pops')} | {_cell(x, 'jitter')} | {_cell(x, 'slide')} | "
            f"{100 * x['skate']:.1f}% | {100 * x['skid']:.0f}% | {path} | {drift} | {faded} | {top} |"
        )
    return lines + [""]
