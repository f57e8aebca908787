"""`python -m models.eval [--final] [--quick] [--methods ...]`: the sealed evaluation (`sealed.py`).

Without `--final` (`make eval`) it scores the VALIDATION inputs into out/eval-val/, where every
choice is made. `--final` (`make eval-final`) scores the sealed test inputs, writes
docs/evaluation.md and docs/eval/results.json, and appends a line to docs/eval/final_runs.md:
run it once a change is finished, never to choose between changes."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from .sealed import evaluate


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m models.eval", description=__doc__)
    ap.add_argument("--final", action="store_true", help="score the sealed test inputs and record the run")
    ap.add_argument("--quick", action="store_true", help="two clips a source, two styles (a smoke run)")
    ap.add_argument("--methods", nargs="+", default=None, help="only these methods (default: every committed one)")
    ap.add_argument("--out", type=Path, default=None, help="output folder (default docs/ or out/eval-val)")
    a = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    r = evaluate(final=a.final, quick=a.quick, methods=tuple(a.methods) if a.methods else None, out=a.out)
    for row in r["rows"]:
        if row["gates"]:
            print(
                f"{row['source']:10s} {row['variant']:9s} {row['session']:7s} {row['style']:10s} "
                f"style {row['style_acc']['share']:.2f} plausible {row['plausible']['share']:.2f} "
                f"jitter {row['jitter_p90']:.2f} {'pass' if row['gates']['all'] else 'fail'}"
            )
    print(f"done in {r['meta']['seconds']} s")


if __name__ == "__main__":
    main()
