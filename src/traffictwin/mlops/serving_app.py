"""The scoring server with bounds before parsing: request size and JSON nesting are refused
before MLflow reads the body as JSON.

``mlflow models serve`` runs ``uvicorn mlflow.pyfunc.scoring_server.app:app``: MLflow reads the
whole body into memory and ``json.loads`` it before the model's ``predict`` sees anything, and it
offers no hook in between (no body-size limit, no nesting limit; a body nested deeper than
Python's recursion limit raises ``RecursionError`` there, answered with HTTP 500; a bool in the
inputs is cast to 1.0 / 0.0 by the signature before ``predict`` sees it). The model's
own checks (:mod:`traffictwin.mlops.serving`: batch size, shape, values) therefore only run after
a request of any size was parsed. To refuse earlier, serve the same model with this app:

.. code-block:: bash

    TRAFFICTWIN_SERVE_MODEL=models:/traffictwin-risk@champion \\
        uvicorn traffictwin.mlops.serving_app:app --host 127.0.0.1 --port 5001

It wraps MLflow's app (same routes and answers) in :func:`bounded`, which, on ``POST``:

- refuses a body over :func:`max_request_bytes` with HTTP 413 — from ``Content-Length`` before
  reading, and while reading (chunked bodies): at most the limit is ever buffered;
- refuses JSON nested deeper than :data:`MAX_DEPTH` (``[``/``{`` minus ``]``/``}``, counted with
  numpy over the bytes, brackets inside strings included) with HTTP 400;
- refuses ``true`` / ``false`` anywhere in the body with HTTP 400: MLflow's parser casts a bool
  to 1.0 / 0.0 by the signature before ``predict`` could tell (the served model takes numbers
  only, and its one param, ``max_batch``, is an integer);

each with MLflow's error body ``{"error_code": "INVALID_PARAMETER_VALUE", "message": ...}``.
"""

from __future__ import annotations

import json
import os
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

import numpy as np

ENV_MODEL = "TRAFFICTWIN_SERVE_MODEL"
ENV_MAX_BYTES = "TRAFFICTWIN_SERVE_MAX_BYTES"
#: deepest JSON nesting a request may have: {"inputs": 4-D array, "params": {...}} needs 5
MAX_DEPTH = 16
#: bytes one number may take in a request's JSON ("-0.123456789," is 13)
BYTES_PER_VALUE = 16
#: bytes of a request beyond its numbers (keys, params, whitespace)
OVERHEAD_BYTES = 1 << 20
#: the limit when the model's signature does not say how many values a sample has
DEFAULT_MAX_BYTES = 64 << 20

Scope = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[dict]]
Send = Callable[[dict], Awaitable[None]]
App = Callable[[Scope, Receive, Send], Awaitable[None]]


def max_request_bytes(values_per_sample: int | None = None) -> int:
    """Largest request body (bytes): ``TRAFFICTWIN_SERVE_MAX_BYTES``, else room for
    :func:`traffictwin.mlops.serving.max_batch` samples of ``values_per_sample`` numbers at
    :data:`BYTES_PER_VALUE` bytes each plus :data:`OVERHEAD_BYTES` (:data:`DEFAULT_MAX_BYTES`
    when the count is unknown). ``ValueError`` names the variable if it is not a positive integer."""
    from traffictwin.mlops.serving import max_batch

    raw = os.environ.get(ENV_MAX_BYTES, "").strip()
    if raw:
        if not raw.isdigit() or int(raw) < 1:
            raise ValueError(f"{ENV_MAX_BYTES}: expected a positive integer of bytes, got {raw!r}")
        return int(raw)
    if not values_per_sample:
        return DEFAULT_MAX_BYTES
    return max_batch() * int(values_per_sample) * BYTES_PER_VALUE + OVERHEAD_BYTES


def nesting_depth(body: bytes) -> int:
    """Deepest ``[``/``{`` nesting of ``body`` (brackets in strings count too: an upper bound)."""
    if not body:
        return 0
    b = np.frombuffer(body, np.uint8)
    step = (b == ord("[")).astype(np.int8) + (b == ord("{"))
    step -= (b == ord("]")).astype(np.int8) + (b == ord("}"))
    return int(np.cumsum(step, dtype=np.int32).max(initial=0))


async def _answer(send: Send, status: int, message: str) -> None:
    body = json.dumps({"error_code": "INVALID_PARAMETER_VALUE", "message": message}).encode()
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(body)).encode()),
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})


def bounded(app: App, max_bytes: int, max_depth: int = MAX_DEPTH) -> App:
    """``app`` behind the size (HTTP 413) and nesting (HTTP 400) checks of the module doc."""

    async def wrapped(scope: Scope, receive: Receive, send: Send) -> None:
        if scope.get("type") != "http" or scope.get("method") != "POST":
            await app(scope, receive, send)
            return
        declared = dict(scope.get("headers") or []).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > max_bytes:
            await _answer(
                send,
                413,
                f"request body of {int(declared)} bytes, more than the limit of {max_bytes} "
                f"({ENV_MAX_BYTES} of the server); split the request",
            )
            return
        chunks, size = [], 0
        while True:
            msg = await receive()
            if msg["type"] != "http.request":
                return  # the client left
            chunk = msg.get("body", b"")
            size += len(chunk)
            if size > max_bytes:
                await _answer(
                    send,
                    413,
                    f"request body over the limit of {max_bytes} bytes ({ENV_MAX_BYTES} of the "
                    "server); split the request",
                )
                return
            chunks.append(chunk)
            if not msg.get("more_body"):
                break
        body = b"".join(chunks)
        if b"true" in body or b"false" in body:
            await _answer(
                send,
                400,
                "request JSON holds true/false; expected numbers (a bool is not a number: "
                "MLflow would cast it to 1.0 / 0.0)",
            )
            return
        depth = nesting_depth(body)
        if depth > max_depth:
            await _answer(
                send,
                400,
                f"request JSON nested {depth} levels deep, more than {max_depth}; expected "
                '{"inputs": <array of the model signature>, "params": {...}}',
            )
            return
        replayed = False

        async def replay() -> dict:
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await app(scope, replay, send)

    return wrapped


def values_per_sample(model: Any) -> int | None:
    """Numbers in one sample of ``model``'s input signature (a pyfunc model), or None."""
    try:
        spec = model.metadata.get_input_schema().inputs[0]
        shape = [int(s) for s in spec.shape[1:]]
    except (AttributeError, IndexError, TypeError):
        return None
    return int(np.prod(shape)) if shape and all(s > 0 for s in shape) else None


def build(model_uri: str) -> App:
    """MLflow's scoring app for ``model_uri`` (a pyfunc model), behind :func:`bounded`."""
    import mlflow.pyfunc
    from mlflow.pyfunc import scoring_server

    model = mlflow.pyfunc.load_model(model_uri)
    return bounded(scoring_server.init(model), max_request_bytes(values_per_sample(model)))


def __getattr__(name: str) -> Any:
    """``app``: the bounded app of ``$TRAFFICTWIN_SERVE_MODEL``, built when uvicorn asks for it."""
    if name != "app":
        raise AttributeError(name)
    uri = os.environ.get(ENV_MODEL)
    if not uri:
        raise RuntimeError(f"{ENV_MODEL}: set it to the model to serve (models:/name@alias)")
    app = build(uri)
    globals()["app"] = app
    return app
