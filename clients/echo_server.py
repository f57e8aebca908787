"""A plain WebSocket echo server on the service's stack (uvicorn + Starlette, same route), the
transport floor the load test compares the service against."""

from __future__ import annotations

import argparse

import uvicorn
from starlette.applications import Starlette
from starlette.routing import WebSocketRoute
from starlette.websockets import WebSocket, WebSocketDisconnect


async def echo(ws: WebSocket) -> None:
    await ws.accept()
    try:
        while True:
            message = await ws.receive()
            if message["type"] == "websocket.disconnect":
                return
            if message.get("bytes") is not None:
                await ws.send_bytes(message["bytes"])
            elif message.get("text") is not None:
                await ws.send_text(message["text"])
    except WebSocketDisconnect:
        return


app = Starlette(routes=[WebSocketRoute("/v1/stream", echo)])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=8001)
    args = parser.parse_args(argv)
    uvicorn.run(app, host=args.host, port=args.port, log_level="warning", ws_per_message_deflate=False)


if __name__ == "__main__":
    main()
