"""Throughput of one SDK session: one frame in flight (`stylise`) against pipelined sends
(`send`/`receive` with `max_in_flight` = depth), as fast as the server answers.

One in flight, every frame costs a full round trip (client send, server step, reply, client
decode) with both ends idle in turn; pipelined, the next frames are already queued at the server
while a reply travels back, so the two ends overlap.

    python -m clients.sdk_bench                       # starts `stylestream serve` on a free port
    python -m clients.sdk_bench --url http://127.0.0.1:8000 --model erd --depths 1,2,4,8
"""

from __future__ import annotations

import argparse
import contextlib
import time

import numpy as np

from .sdk import Client


def run(url: str, model: str, style: str, root: np.ndarray, rot: np.ndarray, depth: int) -> tuple[float, float]:
    """Frames per second and mean round trip (ms) of one session streaming all frames at `depth`."""
    n = len(root)
    with Client(url).session(model=model, style=style, max_in_flight=depth) as session:
        for t in range(min(30, n)):  # warm: the first frames pay for connection set-up and caches
            session.stylise(root[t], rot[t])
        sent_at = np.zeros(n)
        back_at = np.zeros(n)
        t0 = time.perf_counter()
        if depth == 1:
            for t in range(n):
                sent_at[t] = time.perf_counter()
                session.stylise(root[t], rot[t])
                back_at[t] = time.perf_counter()
        else:
            first = session.seq
            for t in range(n):
                sent_at[t] = time.perf_counter()
                session.send(root[t], rot[t])
                for frame in session.poll():
                    back_at[frame.seq - first] = time.perf_counter()
            while session.in_flight:
                frame = session.receive()
                back_at[frame.seq - first] = time.perf_counter()
        elapsed = time.perf_counter() - t0
    return n / elapsed, float(np.mean(back_at - sent_at) * 1000)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m clients.sdk_bench", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--url", help="a running server (default: start one here)")
    parser.add_argument("--model", default="lti")
    parser.add_argument("--style", help="default: the model's first")
    parser.add_argument("--frames", type=int, default=600)
    parser.add_argument("--depths", default="1,2,4,8", help="frames in flight to compare (1 = stylise)")
    parser.add_argument("--repeats", type=int, default=3, help="runs per depth; the median is printed")
    args = parser.parse_args(argv)

    from .loadtest import first_style, real_frames, spawned_server

    root, rot = real_frames(args.frames)
    with contextlib.ExitStack() as stack:
        if args.url:
            url = args.url.rstrip("/")
        else:
            ws_url, _ = stack.enter_context(spawned_server())
            url = ws_url.replace("ws://", "http://", 1).removesuffix("/v1/stream")
        style = args.style or first_style(url.replace("http://", "ws://", 1) + "/v1/stream", args.model)
        depths = [int(d) for d in args.depths.split(",")]
        print(f"{args.model}/{style}, {args.frames} frames per run, median of {args.repeats} runs (depths taken in turn, "
              f"so a busy machine slows each alike), {url}")
        runs: dict[int, list[tuple[float, float]]] = {d: [] for d in depths}
        for _ in range(args.repeats):
            for depth in depths:
                runs[depth].append(run(url, args.model, style, root, rot, depth))
        base = None
        for depth in depths:
            fps, rtt = sorted(runs[depth])[len(runs[depth]) // 2]
            base = base or fps
            label = "one in flight (stylise)" if depth == 1 else f"pipelined, {depth} in flight"
            print(f"{label:28s} {fps:8.0f} frames/s  x{fps / base:4.2f}   mean send->reply {rtt:6.2f} ms")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
