"""`python -m models.eval [--quick]`: score identity and every committed method; write
docs/evaluation.md, docs/eval/results.json and docs/eval/grid_<style>.png."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from .run import evaluate


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m models.eval", description=__doc__)
    ap.add_argument("--quick", action="store_true", help="tiny subset (4 clips, 2 styles, 60 frames)")
    ap.add_argument("--per-content", type=int, default=4, help="test clips per content (default 4)")
    ap.add_argument("--frames", type=int, default=150, help="frames per clip (default 150)")
    ap.add_argument(
        "--out", type=Path, default=None, help="output folder (default docs/, or out/eval-quick with --quick)"
    )
    ap.add_argument("--no-grids", action="store_true")
    a = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    r = evaluate(quick=a.quick, per_content=a.per_content, frames=a.frames, out_dir=a.out, grids=not a.no_grids)
    for name, m in r["methods"].items():
        o = m["overall"]
        print(
            f"{name:9s} style {o['style_acc']:.2f}  content {o['content_acc']:.2f}  FMD {o['fmd']:.1f}  "
            f"skate {o['skate_ratio']:.2f}  path {o['path_dev_cm']:.1f} cm"
        )
    print(f"done in {r['meta']['seconds']} s")


if __name__ == "__main__":
    main()
