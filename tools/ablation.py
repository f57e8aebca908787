"""`python -m tools.ablation [--methods lti erd lpn] [--out DIR]`: does each stage earn its place?

Every stage after a method's core is fitted from data and can be switched off
(`Settings.stages_off`). This scores the VALIDATION inputs (never the test split) with the
shipped pipeline and once more with each declared stage off, and writes what switching it off
changes per source, session and style: style and content reads, plausible clips (percentage
points), pops (points of frames), jitter p90 and the slide ratio. A stage that costs more than
it buys on validation is one to drop or refit; the table is how that is seen, not guessed.

Each evaluation is a separate process (`python -m models.eval`), since a method reads its stages
off once, at load: a few minutes per stage on two cores.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

Key = tuple[str, str, str]  # source, session, style
METRICS: dict[str, tuple[Callable[[dict], float], float]] = {
    # name: (value of a result row, scale shown: 100 for shares as points)
    "style": (lambda r: r["style_acc"]["share"], 100.0),
    "content": (lambda r: (r.get("content_acc") or {}).get("share", float("nan")), 100.0),
    "plausible": (lambda r: r["plausible"]["share"], 100.0),
    "pops": (lambda r: r["pops"], 100.0),
    "jitter": (lambda r: r["jitter_p90"], 1.0),
    "slide": (lambda r: r["slide_ratio"], 1.0),
}


def declared_stages(method: str) -> tuple[str, ...]:
    """The names of the stages `method` declares after its core, in order."""
    where = {"lti": "models.lti", "erd": "models.erd.stages", "lpn": "models.lpn.runtime"}[method]
    stages = importlib.import_module(where).STAGES
    return tuple(s if isinstance(s, str) else s.name for s in stages)


def evaluate(method: str, off: tuple[str, ...], out: Path) -> Path:
    """Run the validation evaluation of `method` with the stages `off` switched off into `out`;
    the path of its results.json."""
    env = {**os.environ, "STYLESTREAM_STAGES_OFF": json.dumps([f"{method}.{s}" for s in off])}
    cmd = [sys.executable, "-m", "models.eval", "--methods", method, "--out", str(out)]
    subprocess.run(cmd, env=env, check=True, stdout=subprocess.DEVNULL)
    return out / "eval" / "results.json"


def method_rows(results: dict, method: str) -> dict[Key, dict]:
    """The shipped method's rows of one evaluation's results, by (source, session, style)."""
    return {(r["source"], r["session"], r["style"]): r for r in results["rows"] if r["variant"] == method}


def changes(shipped: dict[Key, dict], without: dict[Key, dict]) -> dict[Key, dict[str, float]]:
    """Per row both evaluations have, each metric without the stage minus with it (shown scale)."""
    return {
        key: {name: (value(without[key]) - value(row)) * scale for name, (value, scale) in METRICS.items()}
        for key, row in shipped.items()
        if key in without
    }


def table(stage: str, delta: dict[Key, dict[str, float]]) -> str:
    """A markdown table of `changes` for one stage switched off."""
    head = "| source | session | style | " + " | ".join(f"Δ {m}" for m in METRICS) + " |"
    lines = [f"### without {stage}", "", head, "|" + "---|" * (3 + len(METRICS))]
    for (source, session, style), d in sorted(delta.items()):
        cells = " | ".join("–" if v != v else f"{v:+.1f}" if m != "jitter" else f"{v:+.2f}" for m, v in d.items())
        lines.append(f"| {source} | {session} | {style} | {cells} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m tools.ablation", description=__doc__)
    ap.add_argument("--methods", nargs="+", default=["lti", "erd", "lpn"])
    ap.add_argument("--out", type=Path, default=Path("out/ablation"))
    a = ap.parse_args()
    for method in a.methods:
        base = method_rows(json.loads(evaluate(method, (), a.out / method / "shipped").read_text()), method)
        report = [f"# {method}: each stage switched off, validation (`python -m tools.ablation`)\n"]
        for stage in declared_stages(method):
            path = evaluate(method, (stage,), a.out / method / stage)
            report.append(table(stage, changes(base, method_rows(json.loads(path.read_text()), method))))
            (a.out / f"{method}.md").write_text("\n".join(report))
            print(report[-1], flush=True)


if __name__ == "__main__":
    main()
