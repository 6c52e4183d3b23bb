"""Calling an ASGI app in-process, as an HTTP client would (the serving tests)."""

from __future__ import annotations

import asyncio
import json


def asgi_call(app, path: str, body: bytes, method: str = "POST") -> tuple[int, dict]:
    """``method`` ``body`` (JSON bytes) to ``path`` of the ASGI ``app``; (status, JSON body).
    The answer is parsed as strict JSON: a NaN or Infinity in it fails the parse."""
    sent: list[dict] = []

    async def run() -> None:
        delivered = False

        async def receive() -> dict:
            nonlocal delivered
            if not delivered:
                delivered = True
                return {"type": "http.request", "body": body, "more_body": False}
            await asyncio.Event().wait()  # the client never disconnects
            return {"type": "http.disconnect"}

        async def send(message: dict) -> None:
            sent.append(message)

        scope = {
            "type": "http",
            "asgi": {"version": "3.0"},
            "http_version": "1.1",
            "method": method,
            "scheme": "http",
            "path": path,
            "raw_path": path.encode(),
            "query_string": b"",
            "root_path": "",
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(body)).encode()),
            ],
            "client": ("127.0.0.1", 12345),
            "server": ("127.0.0.1", 5000),
        }
        await app(scope, receive, send)

    asyncio.run(run())
    status = next(m["status"] for m in sent if m["type"] == "http.response.start")
    text = b"".join(m.get("body", b"") for m in sent if m["type"] == "http.response.body")
    return status, json.loads(text, parse_constant=_refuse_constant)


def _refuse_constant(name: str) -> float:
    raise ValueError(f"non-standard JSON constant {name} in the answer")
