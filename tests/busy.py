"""Run a command beside busy processes: what "the tests pass on a loaded machine" means here.

    .venv/bin/python -m tests.busy 4 -- .venv/bin/python -m pytest -q tests/test_hostile.py
    make test-loaded                                  # the whole suite beside four

Each busy process spins at normal priority until the command ends, so everything the service does
at a lower one (uploads: `service.background`) competes with them as it would with another job on
the same machine. Four on the 2-core machine is twice the cores' worth of load.
"""

from __future__ import annotations

import argparse
import multiprocessing
import subprocess
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from multiprocessing.synchronize import Event


def _spin(stop: Event) -> None:
    while not stop.is_set():
        for _ in range(100_000):
            pass


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("processes", type=int, help="busy processes beside the command")
    ap.add_argument("command", nargs=argparse.REMAINDER, help="-- then the command")
    args = ap.parse_args()
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        ap.error("no command given")
    stop = multiprocessing.Event()
    spinners = [multiprocessing.Process(target=_spin, args=(stop,), daemon=True) for _ in range(args.processes)]
    for p in spinners:
        p.start()
    try:
        return subprocess.call(command)
    finally:
        stop.set()
        for p in spinners:
            p.join()


if __name__ == "__main__":
    sys.exit(main())
