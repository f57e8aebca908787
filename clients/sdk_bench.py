"""Throughput of one SDK session: one frame in flight (`stylise`) against pipelined sends
(`send`/`receive` with `max_in_flight` = depth), as fast as the server answers.

One in flight, every frame costs a full round trip (client send, network, server step, reply,
client decode) with each end idle in turn; pipelined, the next frames are already on their way or
queued at the server while a reply travels back. `--latency-ms` puts a proxy in between that holds
every chunk that long each way, as a network would: loopback alone hides what a game client a few
milliseconds from its server waits.

    python -m clients.sdk_bench                       # starts `stylestream serve` on a free port
    python -m clients.sdk_bench --latency-ms 5        # ... behind a 5 ms (each way) proxy
    python -m clients.sdk_bench --url http://127.0.0.1:8000 --model erd --depths 1,2,4,8
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import threading
import time
from collections.abc import Iterator

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


async def _delayed_pipe(reader: asyncio.StreamReader, writer: asyncio.StreamWriter, delay_s: float) -> None:
    """Pass bytes on in order, each chunk `delay_s` after it arrived."""
    loop = asyncio.get_running_loop()
    chunks: asyncio.Queue[tuple[float, bytes]] = asyncio.Queue()

    async def take() -> None:
        while data := await reader.read(65536):
            chunks.put_nowait((loop.time() + delay_s, data))
        chunks.put_nowait((loop.time() + delay_s, b""))

    taker = asyncio.create_task(take())
    try:
        while True:
            due, data = await chunks.get()
            await asyncio.sleep(max(0.0, due - loop.time()))
            if not data:
                break
            writer.write(data)
            await writer.drain()
    finally:
        taker.cancel()
        writer.close()


@contextlib.contextmanager
def delay_proxy(target_port: int, delay_s: float) -> Iterator[int]:
    """A loopback TCP proxy to `target_port` adding `delay_s` each way; yields its port."""
    loop = asyncio.new_event_loop()
    started: dict[str, int] = {}
    ready = threading.Event()
    stop = asyncio.Event()

    async def connection(client_r: asyncio.StreamReader, client_w: asyncio.StreamWriter) -> None:
        server_r, server_w = await asyncio.open_connection("127.0.0.1", target_port)
        try:
            await asyncio.gather(
                _delayed_pipe(client_r, server_w, delay_s),
                _delayed_pipe(server_r, client_w, delay_s),
                return_exceptions=True,
            )
        except asyncio.CancelledError:  # the proxy is closing: end quietly (asyncio's server callback reads
            pass  # a cancelled connection task's exception and would print it)

    async def serve() -> None:
        server = await asyncio.start_server(connection, "127.0.0.1", 0)
        started["port"] = server.sockets[0].getsockname()[1]
        ready.set()
        await stop.wait()
        server.close()
        others = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
        for task in others:
            task.cancel()
        await asyncio.gather(*others, return_exceptions=True)

    thread = threading.Thread(target=loop.run_until_complete, args=(serve(),), daemon=True)
    thread.start()
    ready.wait(10)
    try:
        yield started["port"]
    finally:
        loop.call_soon_threadsafe(stop.set)
        thread.join(timeout=10)
        loop.close()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m clients.sdk_bench", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--url", help="a running server (default: start one here)")
    parser.add_argument("--model", default="lti")
    parser.add_argument("--style", help="default: the model's first")
    parser.add_argument("--frames", type=int, default=600)
    parser.add_argument("--depths", default="1,2,4,8", help="frames in flight to compare (1 = stylise)")
    parser.add_argument("--repeats", type=int, default=3, help="runs per depth; the median is printed")
    parser.add_argument(
        "--latency-ms",
        type=float,
        default=0.0,
        help="one-way delay of a proxy between client and server (default 0: straight to the server)",
    )
    args = parser.parse_args(argv)

    from .loadtest import first_style, real_frames, spawned_server

    root, rot = real_frames(args.frames)
    with contextlib.ExitStack() as stack:
        if args.url:
            url = args.url.rstrip("/")
        else:
            ws_url, _ = stack.enter_context(spawned_server())
            url = ws_url.replace("ws://", "http://", 1).removesuffix("/v1/stream")
        if args.latency_ms > 0:
            port = int(url.rsplit(":", 1)[1].split("/")[0])
            url = f"http://127.0.0.1:{stack.enter_context(delay_proxy(port, args.latency_ms / 1000))}"
        style = args.style or first_style(url.replace("http://", "ws://", 1) + "/v1/stream", args.model)
        depths = [int(d) for d in args.depths.split(",")]
        print(
            f"{args.model}/{style}, {args.frames} frames per run, {args.latency_ms:g} ms each way, median of {args.repeats} runs (depths taken in turn, "
            f"so a busy machine slows each alike), {url}"
        )
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
