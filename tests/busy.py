"""Run a command beside busy processes: what "the tests pass on a loaded machine" means here.

    .venv/bin/python -m tests.busy 4 -- .venv/bin/python -m pytest -q tests/test_hostile.py
    make test-loaded                                  # the whole suite beside four

Each busy process spins at normal priority until the command ends, so everything the service does
at a lower one (uploads: `service.background`) competes with them as it would with another job on
the same machine. Four on the 2-core machine is twice the cores' worth of load.
"""

from __future__ import annotations

import argparse
import subprocess
import sys

from clients.hostile_bench import busy_processes


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("processes", type=int, help="busy processes beside the command")
    ap.add_argument("command", nargs=argparse.REMAINDER, help="-- then the command")
    args = ap.parse_args()
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        ap.error("no command given")
    with busy_processes(args.processes):
        return subprocess.call(command)


if __name__ == "__main__":
    sys.exit(main())
