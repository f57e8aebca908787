"""`stylestream` command line: one entry point, a subcommand per job.

    stylestream serve                      start the service (health, models) on 127.0.0.1:8000
    stylestream data summary               what the mocap data holds (files, frames, styles x contents)
    stylestream data warm                  unpack and parse all data into the cache, timed
    stylestream data fetch [--from URL]    unpack the mocap archives into the cache (downloading missing ones), once
    stylestream render a.bvh [b.bvh] -o x.gif   render motions side by side (GIF, or PNG contact sheet)
    stylestream retarget in.bvh -o out.bvh      any humanoid BVH -> Bandai Namco skeleton (30 fps)
    stylestream loadtest --sessions 1,64 --echo-floor   open-loop latency test against a server it starts
    stylestream soak --minutes 30 --sessions 16         long run sampling server memory (docs/soak.md)
    stylestream styles add clip.bvh --name proud --model all   a new style from a clip, its jobs followed

Every subcommand has --help. Settings (data folder, cache folder, port...) come from
STYLESTREAM_* environment variables or a .env file; see README.md.
"""

from __future__ import annotations

import argparse
import sys


def _data(args: argparse.Namespace) -> int:
    from models.data.__main__ import main as data_main

    options = sum((["--dataset", d] for d in args.dataset or []), [])
    if args.action == "fetch":
        options += ["--from", args.source] if args.source else []
        options += ["--data-dir", str(args.data_dir)] if args.data_dir else []
    elif args.source or args.data_dir:
        print(f"stylestream data {args.action}: --from and --data-dir go with 'fetch'", file=sys.stderr)
        return 2
    return data_main([args.action] + options)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="stylestream", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    from service.cli import add_serve_command

    add_serve_command(sub)  # the server's own entry point, where the server lives

    p = sub.add_parser("data", help="make the mocap data ready, inspect it or build its parse cache")
    p.add_argument(
        "action",
        choices=["summary", "warm", "fetch"],
        help="summary: tables; warm: unpack + parse everything, timed; fetch: unpack the archives "
        "into the cache (downloading missing ones with --from), once",
    )
    p.add_argument(
        "--dataset", action="append", help="limit to a dataset (repeatable): bandai-namco-1, bandai-namco-2, xia, cmu"
    )
    p.add_argument(
        "--from",
        dest="source",
        metavar="URL",
        help="fetch: download archives the data folder lacks from URL/<archive> (checked against their known SHA-256)",
    )
    p.add_argument("--data-dir", help="fetch: the data folder (default: STYLESTREAM_DATA_DIR, else ../shared/data)")
    p.set_defaults(func=_data)

    from .loadtest import add_loadtest_command
    from .motion_tools import add_motion_commands
    from .soak import add_soak_command
    from .styles_cli import add_styles_command
    from .vmc import add_vmc_command

    add_motion_commands(sub)
    add_loadtest_command(sub)
    add_soak_command(sub)
    add_styles_command(sub)
    add_vmc_command(sub)
    return parser


USER_ERRORS = (
    ("models.motion.bvh", "BvhError"),
    ("models.motion.humanoid", "RigError"),
    ("models.data.archives", "DataError"),
    ("httpx", "HTTPError"),
    ("websockets.exceptions", "WebSocketException"),
    ("clients.sdk_types", "ServerError"),
    ("clients.sdk_types", "ResumeError"),
)


def user_errors() -> tuple[type[BaseException], ...]:
    """Exceptions a user can cause and fix: a malformed or missing file, missing mocap data, a port
    in use, a server that refuses or cannot be reached. Only the classes of modules already
    imported: one never imported cannot have been raised, and importing them all (torch, through
    the rig code) added 2 s to a one-line error."""
    found = [getattr(sys.modules[module], name) for module, name in USER_ERRORS if module in sys.modules]
    return (OSError, *found)


def main(argv: list[str] | None = None) -> int:
    """Run a subcommand; a user error (`user_errors`) ends in one line naming the problem and exit
    status 2, not a traceback. So does a plain `pip install stylestream` (the SDK alone), whose
    commands lack the server's packages: the line says which extra to install."""
    try:
        args = build_parser().parse_args(argv)
        try:
            return args.func(args)
        except user_errors() as exc:  # evaluated only when something was raised
            print(f"stylestream {args.command}: error: {exc}", file=sys.stderr)
            return 2
    except ModuleNotFoundError as exc:
        if not exc.name or exc.name.split(".")[0] in ("clients", "models", "service"):
            raise  # a broken install of this project itself, not a missing extra
        print(
            f"stylestream: {exc.name} is not installed; the commands need the server's packages: "
            "pip install 'stylestream[server]'",
            file=sys.stderr,
        )
        return 2


if __name__ == "__main__":
    sys.exit(main())
