"""Time from upload to live, per method: one real walk clip of each dataset-1 style that no model
trained on is uploaded to every model through `Client.add_style` (fine-tuning on), and the command
prints, per model and style, the seconds until the style could be streamed (`live`) and until its
job finished (`job`), or the model's refusal; then the median per model.

    python -m clients.upload_bench [--styles proud,giant] [--url http://127.0.0.1:8000]

Without --url it starts `stylestream serve` on a free port with an empty styles folder, so the
uploads leave nothing behind. The machine's load is printed beside the figures: the jobs share
its cores with everything else running.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import tempfile
from collections.abc import Iterator

from .sdk import AddedStyle, Client

HELD_OUT = ("happy", "sad", "angry", "proud", "not-confident", "musical", "giant", "chimpira")


def walk_clip(style: str):
    """The first dataset-1 straight walk of `style` (the upload a user would make)."""
    from models.data import build_index, select

    clips = select(build_index(["bandai-namco-1"]), dataset="bandai-namco-1", style=style, content="walk")
    if not clips:
        raise SystemExit(f"no dataset-1 walk of style {style!r}")
    return clips[0]


@contextlib.contextmanager
def server(url: str | None) -> Iterator[str]:
    if url:
        yield url
        return
    from .loadtest import spawned_server

    with tempfile.TemporaryDirectory() as styles, spawned_server(env={"STYLESTREAM_STYLES_DIR": styles}) as (ws, _):
        yield ws.replace("ws://", "http://").removesuffix("/v1/stream")


def row(style: str, added: AddedStyle) -> str:
    if added.style is None:
        return f"{added.model:<4} {style:<14} refused  {getattr(added.error, 'code', added.error)}"
    live = "   -  " if added.live_s is None else f"{added.live_s:6.1f}"
    job = "   -  " if added.done_s is None else f"{added.done_s:6.1f}"
    note = "" if added.error is None else f"  ({added.error})"
    return f"{added.model:<4} {style:<14} live {live} s  job {job} s  {added.style.status}{note}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--styles", default=",".join(HELD_OUT), help="dataset-1 styles to upload (comma-separated)")
    parser.add_argument("--url", help="a running server (default: start one with an empty styles folder)")
    parser.add_argument("--timeout", type=float, default=300.0, help="longest wait for one style's jobs")
    args = parser.parse_args()
    styles = [s for s in args.styles.split(",") if s]
    clips = {s: walk_clip(s) for s in styles}
    print(f"load average {' '.join(f'{x:.1f}' for x in os.getloadavg())} on {os.cpu_count()} cores")
    outcomes: list[AddedStyle] = []
    with server(args.url) as base, Client(base, timeout=60) as client:
        for style, clip in clips.items():
            added = client.add_style(f"bench-{style}", bvh=clip.path, timeout=args.timeout)
            for outcome in added.values():
                print(row(style, outcome), flush=True)
                outcomes.append(outcome)
                if outcome.style is not None:
                    client.delete_style(outcome.style.id)
    print("median per model (s):")
    for model in sorted({o.model for o in outcomes}):
        mine = [o for o in outcomes if o.model == model]
        live = [o.live_s for o in mine if o.live_s is not None]
        done = [o.done_s for o in mine if o.done_s is not None]
        refused = sum(o.style is None for o in mine)
        print(
            f"{model:<4} live {statistics.median(live) if live else float('nan'):6.1f}  "
            f"job {statistics.median(done) if done else float('nan'):6.1f}  "
            f"({len(live)} of {len(mine)} live, {refused} refused)"
        )


if __name__ == "__main__":
    main()
