"""Where a single-character frame's server CPU goes beyond the transport's (issue 17's 1.3x target):
the echo server, the service, and the same service with every model's step replaced by an
identity (output = input frame, state untouched), alternated in one run at N spread sessions.

    python -m clients.floor_bench --sessions 64 --rounds 2 --model lti

The identity variant keeps everything else on the frame path (decode, validation, skeleton
mapping, the batcher, session bookkeeping, metrics, encode, the socket write), so
service - identity is what the model step costs and identity - echo what the service's own
per-frame path costs over a bare echo on the same stack."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator
from contextlib import contextmanager

from .loadtest import Result, _cpu_seconds, _spawn, free_port, run, spawned_server

VARIANTS = ("echo", "service", "identity")


def serve_identity(argv: list[str]) -> None:
    """`stylestream serve` with each loaded model's `step_batch` an identity (the child process)."""
    import models.registry as registry
    from models.interface import FrameBatch

    def _identity_step(state, frames, style_weights):  # on the measured frame path: no import in it
        return FrameBatch(frames.root.copy(), frames.rotations.copy()), state

    load = registry.load_models

    def load_identity(weights_dir):
        models = load(weights_dir)
        for model in models.values():
            model.step_batch = _identity_step  # type: ignore[method-assign]
        return models

    registry.load_models = load_identity
    from . import cli

    cli.main(["serve", "--log-level", "warning", *argv])


@contextmanager
def _server(variant: str) -> Iterator[tuple[str, int]]:
    if variant == "service":
        with spawned_server() as (url, server):
            yield url, server.pid
        return
    port = free_port()
    args = ["clients.echo_server"] if variant == "echo" else ["clients.floor_bench", "serve-identity"]
    proc = _spawn(args, port)
    try:
        yield f"ws://127.0.0.1:{port}/v1/stream", proc.pid
    finally:
        proc.terminate()
        proc.wait(timeout=20)


def measure(variant: str, sessions: int, seconds: float, model: str, style: str) -> tuple[Result, float]:
    """One warmed-up open-loop run at 60 fps; returns it and the server's CPU µs per frame."""
    echo = variant == "echo"
    with _server(variant) as (url, pid):
        run(url, 8, 60.0, 2.0, model, style, echo=echo)  # warm-up: compiled kernels, first batches
        cpu0 = _cpu_seconds(pid)
        result, _ = run(url, sessions, 60.0, seconds, model, style, echo=echo)
        cpu = _cpu_seconds(pid) - cpu0
    return result, 1e6 * cpu / max(result.received, 1)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["serve-identity"]:
        serve_identity(argv[1:])
        return 0
    parser = argparse.ArgumentParser(prog="python -m clients.floor_bench", description=__doc__)
    parser.add_argument("--sessions", type=int, default=64)
    parser.add_argument("--seconds", type=float, default=8.0)
    parser.add_argument("--rounds", type=int, default=2, help="each variant this many times, alternated")
    parser.add_argument("--model", default="lti")
    parser.add_argument("--style", default="elderly")
    args = parser.parse_args(argv)
    cpu: dict[str, list[float]] = {v: [] for v in VARIANTS}
    for _ in range(args.rounds):
        for variant in VARIANTS:
            result, us = measure(variant, args.sessions, args.seconds, args.model, args.style)
            cpu[variant].append(us)
            print(
                f"{variant:8s} {args.sessions} sessions: {us:6.1f} µs server CPU per frame, "
                f"p99 {result.p99_ms:.2f} ms, received {result.received}, dropped {result.dropped}",
                flush=True,
            )
    for variant in VARIANTS:
        ratios = [us / echo for us, echo in zip(cpu[variant], cpu["echo"])]  # against the same round's echo
        print(
            f"{variant:8s} {min(cpu[variant]):6.1f}-{max(cpu[variant]):6.1f} µs per frame, "
            f"{min(ratios):.2f}-{max(ratios):.2f}x echo"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
