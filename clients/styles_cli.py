"""`stylestream styles`: list the server's styles, add one from a clip, remove one.

    stylestream styles add proud.bvh --name proud --model all    upload to every model, follow the jobs
    stylestream styles list [--model lpn]
    stylestream styles rm lti.proud

`add` prints, per model, when the style could first be streamed and when its job finished, so the
time from upload to live is read off the command itself. The SDK's `Client.add_style` does the work;
this module only draws it.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .sdk import AddedStyle, Client, JobInfo

BAR = 24


def progress_line(model: str, job: JobInfo) -> str:
    """One model's job as a text bar, e.g. `lti  [######------------------]  25% running: ...`."""
    done = int(round(BAR * min(max(job.progress, 0.0), 1.0)))
    message = f": {job.message}" if job.message else ""
    return f"{model:<4} [{'#' * done}{'-' * (BAR - done)}] {job.progress:4.0%} {job.status}{message}"


def outcome_line(added: AddedStyle) -> str:
    if added.error is not None and added.style is None:
        return f"{added.model:<4} refused: {added.error}"
    assert added.style is not None
    live = "not yet live" if added.live_s is None else f"live after {added.live_s:.1f} s"
    job = "" if added.done_s is None else f", job finished after {added.done_s:.1f} s"
    failed = "" if added.error is None else f" ({added.error})"
    return f"{added.model:<4} {added.style.id}: {added.style.status}, {live}{job}{failed}"


def _add(args: argparse.Namespace) -> int:
    models = None if args.model == "all" else [args.model]
    tty = sys.stderr.isatty()

    def show(model: str, job: JobInfo) -> None:
        print(("\r" if tty else "") + progress_line(model, job), end="" if tty else "\n", file=sys.stderr, flush=True)

    with Client(args.url, token=args.token) as client:
        added = client.add_style(
            args.name,
            models=models,
            bvh=args.clip,
            fine_tune=not args.no_fine_tune,
            progress=show,
            timeout=args.timeout,
        )
    if tty:
        print(file=sys.stderr)
    for outcome in added.values():
        print(outcome_line(outcome))
    usable = [a for a in added.values() if a.style is not None and a.style.status == "ready"]
    return 0 if usable else 1


def _list(args: argparse.Namespace) -> int:
    with Client(args.url, token=args.token) as client:
        for s in client.styles(args.model):
            print(f"{s.id:<32} {s.kind:<9} {s.status}")
    return 0


def _remove(args: argparse.Namespace) -> int:
    with Client(args.url, token=args.token) as client:
        client.delete_style(args.style_id)
    print(f"removed {args.style_id}")
    return 0


def add_styles_command(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("styles", help="list the server's styles, add one from a clip (following its jobs), remove one")
    actions = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    server = argparse.ArgumentParser(add_help=False)
    server.add_argument("--url", default="http://127.0.0.1:8000", help="server (default http://127.0.0.1:8000)")
    server.add_argument("--token", help="API token, if the server requires one")

    a = actions.add_parser("add", parents=[server], help="a BVH clip (any humanoid rig) as a new style")
    a.add_argument("clip", type=Path, help="BVH file, 5-15 s of the style")
    a.add_argument("--name", required=True, help="the style's name (its id is <model>.<name>)")
    a.add_argument("--model", default="all", help="lti, erd, lpn or all (default: every model that takes uploads)")
    a.add_argument(
        "--no-fine-tune", action="store_true", help="no fine-tuning job (LPN-FiLM's instant style only; LTI needs one)"
    )
    a.add_argument("--timeout", type=float, help="stop waiting for the jobs after this many seconds (they go on)")
    a.set_defaults(func=_add)

    ls = actions.add_parser("list", parents=[server], help="every style, or one model's")
    ls.add_argument("--model", help="only this model's styles")
    ls.set_defaults(func=_list)

    rm = actions.add_parser("rm", parents=[server], help="remove an uploaded style")
    rm.add_argument("style_id", help="<model>.<name>")
    rm.set_defaults(func=_remove)
