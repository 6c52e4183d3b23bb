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

For a risk model it adds ``POST /risk`` (:data:`RISK_PATH`): the risk of one stereo pair as a
user has it, two PNG files, answered with the JSON of ``traffictwin risk LEFT RIGHT --speed S``
by :func:`traffictwin.api.serving.pair_route` (looked up through :data:`ROUTES`): the API's own
chain, :func:`traffictwin.api.assess_risk`, on the model loaded by
:func:`traffictwin.api.load_risk`. Its request (:data:`traffictwin.api.serving.RISK_FIELDS`)::

    {"left_png": "<base64 of the left PNG>", "right_png": "<base64 of the right PNG>",
     "speed_mps": 8.725}

Its body limit is :func:`risk_request_bytes` of the model's camera (two PNGs of that size), the
nesting limit the same; a bad request gets HTTP 400 with one line naming the field. On the app
of another model ``/risk`` answers HTTP 404 with one line. ``/invocations`` is MLflow's, as above.
"""

from __future__ import annotations

import asyncio
import json
import os
from collections.abc import Awaitable, Callable, Mapping, MutableMapping
from dataclasses import dataclass
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
#: the route that answers a stereo pair (risk models only)
RISK_PATH = "/risk"
#: bytes of a PNG beyond its pixels: zlib blocks, chunk headers, ancillary chunks
PNG_OVERHEAD_BYTES = 64 << 10


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


async def _answer(
    send: Send, status: int, message: str, code: str = "INVALID_PARAMETER_VALUE"
) -> None:
    """An error answer with MLflow's error body (``error_code``, one-line ``message``)."""
    await _send_json(send, status, {"error_code": code, "message": message})


async def _send_json(send: Send, status: int, payload: Any) -> None:
    body = json.dumps(payload).encode()
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


@dataclass(frozen=True)
class Route:
    """A ``POST`` route answered by the bounded app itself, not by MLflow's: ``answer`` maps a
    request body (bytes, within ``max_bytes`` and the nesting limit) to ``(HTTP status, JSON
    payload)``; it runs in a worker thread."""

    answer: Callable[[bytes], tuple[int, Any]]
    max_bytes: int


async def _read_body(receive: Receive, send: Send, limit: int) -> bytes | None:
    """The request body, read up to ``limit`` bytes; None when the client left or the body is
    over the limit (answered HTTP 413)."""
    chunks, size = [], 0
    while True:
        msg = await receive()
        if msg["type"] != "http.request":
            return None  # the client left
        chunk = msg.get("body", b"")
        size += len(chunk)
        if size > limit:
            await _answer(
                send,
                413,
                f"request body over the limit of {limit} bytes ({ENV_MAX_BYTES} of the "
                "server); split the request",
            )
            return None
        chunks.append(chunk)
        if not msg.get("more_body"):
            return b"".join(chunks)


def _body_problem(body: bytes, route: Route | None, max_depth: int, scope: Scope) -> str | None:
    """Why ``body`` is refused (HTTP 400): true/false in a model request, or JSON nested deeper
    than ``max_depth`` levels; None when it passes."""
    if route is None and (b"true" in body or b"false" in body):
        return (
            "request JSON holds true/false; expected numbers (a bool is not a number: "
            "MLflow would cast it to 1.0 / 0.0)"
        )
    depth = nesting_depth(body)
    if depth > max_depth:
        expected = (
            f"the JSON object of {scope['path']}"
            if route is not None
            else '{"inputs": <array of the model signature>, "params": {...}}'
        )
        return (
            f"request JSON nested {depth} levels deep, more than {max_depth}; expected " + expected
        )
    return None


def bounded(
    app: App,
    max_bytes: int,
    max_depth: int = MAX_DEPTH,
    routes: Mapping[str, Route] | None = None,
) -> App:
    """``app`` behind the size (HTTP 413) and nesting (HTTP 400) checks of the module doc;
    a ``POST`` to a path of ``routes`` is answered by that :class:`Route` (its own size limit;
    no true/false check: its JSON is not MLflow's), every other request by ``app``."""
    routes = dict(routes or {})

    async def wrapped(scope: Scope, receive: Receive, send: Send) -> None:
        if scope.get("type") != "http" or scope.get("method") != "POST":
            await app(scope, receive, send)
            return
        route = routes.get(scope.get("path", ""))
        limit = route.max_bytes if route is not None else max_bytes
        declared = dict(scope.get("headers") or []).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > limit:
            await _answer(
                send,
                413,
                f"request body of {int(declared)} bytes, more than the limit of {limit} "
                f"({ENV_MAX_BYTES} of the server); split the request",
            )
            return
        body = await _read_body(receive, send, limit)
        if body is None:
            return
        problem = _body_problem(body, route, max_depth, scope)
        if problem is not None:
            await _answer(send, 400, problem)
            return
        if route is not None:
            status, payload = await asyncio.to_thread(route.answer, body)
            await _send_json(send, status, payload)
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


def risk_request_bytes(width: int | None, height: int | None) -> int:
    """Largest ``/risk`` body (bytes): ``TRAFFICTWIN_SERVE_MAX_BYTES`` when set, else room for
    two PNGs of the camera's ``width`` x ``height`` px at their largest (8-bit RGBA stored
    uncompressed: a filter byte and 4 bytes a pixel per row, 1/64 more for zlib and chunk
    framing, plus :data:`PNG_OVERHEAD_BYTES`) in base64 (4 bytes per 3), plus
    :data:`OVERHEAD_BYTES`; :func:`max_request_bytes` of an unknown count when the camera is
    unknown."""
    if os.environ.get(ENV_MAX_BYTES, "").strip() or not (width and height):
        return max_request_bytes()
    png = int(height) * (1 + 4 * int(width))
    png += png // 64 + PNG_OVERHEAD_BYTES
    return 2 * 4 * -(-png // 3) + OVERHEAD_BYTES


# problem -> (path, module, factory) of the routes the app answers itself for a model of that
# problem; the factory (model URI -> Route) is looked up by name, as the problems' loaders in
# traffictwin.mlops.serving are: it lives in the API, a layer above this module
ROUTES = {"risk": (RISK_PATH, "traffictwin.api.serving", "pair_route")}


def not_here(path: str, model_uri: str, why: str, max_bytes: int) -> Route:
    """A route that answers every request with HTTP 404 and one line: ``path`` is not served
    for ``model_uri`` (``why``)."""
    message = f"{path}: not served for {model_uri} ({why})"
    return Route(
        lambda _body: (404, {"error_code": "ENDPOINT_NOT_FOUND", "message": message}), max_bytes
    )


def model_problem(model: Any) -> str | None:
    """The problem (``risk``, ``fusion``...) of a pyfunc model's ``traffictwin`` flavour, or None."""
    from traffictwin.mlops.model_artifact import FLAVOR

    try:
        problem = model.metadata.flavors[FLAVOR]["problem"]
    except (AttributeError, KeyError, TypeError):
        return None
    return problem if isinstance(problem, str) else None


def model_routes(model_uri: str, problem: str | None, max_bytes: int) -> dict[str, Route]:
    """The routes of :data:`ROUTES` for a model of ``problem`` at ``model_uri``: its own
    problem's built by its factory, every other one a :func:`not_here` (HTTP 404) with
    ``max_bytes`` (the app's limit)."""
    import importlib

    routes = {}
    for owner, (path, module, factory) in ROUTES.items():
        if owner == problem:
            routes[path] = getattr(importlib.import_module(module), factory)(model_uri)
        else:
            what = f"a {problem} model" if problem else "not a traffictwin model"
            routes[path] = not_here(
                path, model_uri, f"{what}; {path} answers for a {owner} model", max_bytes
            )
    return routes


def build(model_uri: str) -> App:
    """MLflow's scoring app for ``model_uri`` (a pyfunc model), behind :func:`bounded`, with
    the routes of :func:`model_routes` (``/risk`` for a risk model)."""
    import mlflow.pyfunc
    from mlflow.pyfunc import scoring_server

    # no "Downloading artifacts" bar in the server's log (as the CLI: traffictwin.api.HTTP_ENV)
    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")
    model = mlflow.pyfunc.load_model(model_uri)
    limit = max_request_bytes(values_per_sample(model))
    routes = model_routes(model_uri, model_problem(model), limit)
    return bounded(scoring_server.init(model), limit, routes=routes)


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
