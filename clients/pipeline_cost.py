"""What serving the core pipelines costs: the server's start-up (its lifespan: model loads and
warm-up steps) and resident memory, with `core_pipelines` off and on, each in a fresh process.

    python -m clients.pipeline_cost [--repeats 2]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time


def rss_mb() -> float:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmRSS"):
                return int(line.split()[1]) / 1024
    return float("nan")


def measure(on: bool) -> None:
    """One server start in this process; prints seconds and RSS."""
    from fastapi.testclient import TestClient

    from service.app import create_app
    from service.settings import ServiceSettings

    t0 = time.perf_counter()
    with TestClient(create_app(ServiceSettings(core_pipelines=on))) as client:
        seconds = time.perf_counter() - t0
        offered = {m["name"]: m["pipelines"] for m in client.get("/v1/models").json()}
        print(f"core_pipelines={str(on).lower()}: start-up {seconds:.2f} s, RSS {rss_mb():.0f} MB, {offered}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--one", choices=["true", "false"], help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one is not None:
        measure(args.one == "true")
        return
    for _ in range(args.repeats):
        for on in ("false", "true"):
            subprocess.run([sys.executable, "-m", "clients.pipeline_cost", "--one", on], check=True)


if __name__ == "__main__":
    main()
