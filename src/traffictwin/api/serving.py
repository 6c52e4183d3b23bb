"""The serving app's ``POST /risk``: a stereo pair as a user has it (two PNG files, base64 in
JSON, and the speed) answered with the JSON of ``traffictwin risk LEFT RIGHT --speed S``.

:func:`pair_route` is looked up by name by :mod:`traffictwin.mlops.serving_app` (``ROUTES``)
for a risk model's app. The model is the one the app serves, loaded by :func:`load_risk` (a
registry reference ``models:/name@alias`` or a model folder); a request runs the CLI's chain
(:func:`check_speed`, :func:`stereo_settings`, :func:`assess_risk`: ORB pair check, disparity,
predictor, THW verdict) with the fields of :func:`answered_by`, one request at a time. Every bad
request is HTTP 400 with one line naming the field (:data:`RISK_FIELDS`).
"""

from __future__ import annotations

import base64
import binascii
import json
import logging
import math
import os
import threading
import warnings
from typing import Any

import numpy as np

from traffictwin.mlops.serving_app import (
    RISK_PATH,
    Route,
    not_here,
    risk_request_bytes,
)

from .errors import ApiError, ApiWarning, InputValueError, ModelDomainError
from .images import Frame, decode_png
from .risk import LoadedRisk, answered_by, assess_risk, check_speed, load_risk, stereo_settings

log = logging.getLogger(__name__)
#: the fields of a ``/risk`` request: name -> what it holds
RISK_FIELDS = {
    "left_png": "the left camera's image: base64 (standard alphabet, no line breaks) of a PNG "
    "file's bytes, at the model's camera size",
    "right_png": "the right camera's image, the same way",
    "speed_mps": "the subject vehicle's speed (m/s): a finite number >= 0",
}
#: the learned stereo network for a risk model that reads its disparity and is served by registry
#: reference (the CLI's ``--stereo-model``: a folder or a reference); unset: none
ENV_STEREO_MODEL = "TRAFFICTWIN_SERVE_STEREO_MODEL"
#: the id of the pair in the answer (the CLI's is the left image's file stem)
PAIR_ID = "pair"


class RequestError(ValueError):
    """A ``/risk`` request the route refuses (HTTP 400); the message names the field."""


def _error(status: int, message: str, code: str = "INVALID_PARAMETER_VALUE") -> tuple[int, dict]:
    return status, {"error_code": code, "message": message}


def pair_route(model_uri: str) -> Route:
    """The ``/risk`` :class:`~traffictwin.mlops.serving_app.Route` of the risk model at
    ``model_uri``; a :func:`~traffictwin.mlops.serving_app.not_here` route (HTTP 404, the
    reason) when :func:`load_risk` cannot load it (with ``$TRAFFICTWIN_SERVE_STEREO_MODEL`` as
    its ``stereo_model``)."""
    stereo = os.environ.get(ENV_STEREO_MODEL, "").strip() or None
    try:
        risk = load_risk(model_uri, stereo_model=stereo)
    except ApiError as exc:
        why = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        log.warning("%s: not served: %s", RISK_PATH, why)
        return not_here(RISK_PATH, model_uri, why, risk_request_bytes(None, None))
    scorer = PairScorer(risk)
    cam = scorer.camera
    return Route(scorer.answer, risk_request_bytes(*(cam or (None, None))))


class PairScorer:
    """Answers ``/risk`` bodies for one loaded risk model, one request at a time (a lock: the
    ORB check, SGM and the predictor use every core already)."""

    def __init__(self, risk: LoadedRisk) -> None:
        self.risk = risk
        self.settings = stereo_settings(risk.domain, None, risk.description)
        cam = risk.domain.get("camera")
        self.camera: tuple[int, int] | None = (
            (int(cam["width"]), int(cam["height"]))
            if isinstance(cam, dict) and {"width", "height"} <= set(cam)
            else None
        )
        self._lock = threading.Lock()

    def answer(self, body: bytes) -> tuple[int, Any]:
        """``(HTTP status, JSON payload)`` of a request ``body``: 200 and the pair's JSON, 400
        and one line naming the field, or 500 when the model fails."""
        try:
            left, right, speed = self.parse(body)
            with self._lock:
                return 200, self.score(left, right, speed)
        except (RequestError, InputValueError, ModelDomainError) as exc:
            return _error(400, str(exc))
        except ApiError as exc:
            return _error(500, str(exc), "INTERNAL_ERROR")
        except Exception as exc:  # noqa: BLE001 - one line to the client, the trace to the log
            log.exception("%s failed", RISK_PATH)
            return _error(
                500, f"{RISK_PATH}: internal error ({type(exc).__name__})", "INTERNAL_ERROR"
            )

    def parse(self, body: bytes) -> tuple[np.ndarray, np.ndarray, float]:
        """The left and right BGR images and the speed (m/s) of a request ``body``;
        :class:`RequestError` / :class:`InputValueError` naming the field."""
        expected = ", ".join(RISK_FIELDS)
        try:
            req = json.loads(body)
        except (ValueError, UnicodeDecodeError) as exc:
            raise RequestError(
                f"request body: not valid JSON ({exc}); expected an object of {expected}"
            ) from None
        if not isinstance(req, dict):
            raise RequestError(
                f"request body: expected a JSON object of {expected}, got {type(req).__name__}"
            )
        unknown = sorted(set(req) - set(RISK_FIELDS))
        if unknown:
            raise RequestError(f"unknown field(s) {unknown}; expected {expected}")
        missing = [k for k in RISK_FIELDS if k not in req]
        if missing:
            raise RequestError(
                f"{missing[0]}: missing ({RISK_FIELDS[missing[0]]})"
                + (f"; also missing: {', '.join(missing[1:])}" if missing[1:] else "")
            )
        speed = req["speed_mps"]
        if isinstance(speed, bool) or not isinstance(speed, (int, float)):
            raise RequestError(f"speed_mps: expected a number of m/s, got {json.dumps(speed)[:40]}")
        if not (math.isfinite(speed) and speed >= 0):
            raise RequestError(f"speed_mps: must be a finite speed >= 0 m/s, got {speed}")
        left, right = (self.image(req, k) for k in ("left_png", "right_png"))
        if left.shape != right.shape:
            raise RequestError(
                f"right_png: image {right.shape[1]}x{right.shape[0]} px (W x H) differs from "
                f"left_png's {left.shape[1]}x{left.shape[0]}"
            )
        return left, right, float(speed)

    def image(self, req: dict[str, Any], field: str) -> np.ndarray:
        """The BGR image of ``field``: base64 of a PNG of the model's camera size."""
        text = req[field]
        if not isinstance(text, str):
            raise RequestError(
                f"{field}: expected a string of base64 (a PNG file's bytes), got "
                f"{type(text).__name__}"
            )
        try:
            data = base64.b64decode(text, validate=True)
        except (binascii.Error, ValueError) as exc:
            raise RequestError(f"{field}: not valid base64 ({exc})") from None
        img = decode_png(data, field)
        if self.camera is not None and (img.shape[1], img.shape[0]) != self.camera:
            raise RequestError(
                f"{field}: image {img.shape[1]}x{img.shape[0]} px (W x H), expected the model's "
                f"camera {self.camera[0]}x{self.camera[1]} (domain.camera of {self.risk.description})"
            )
        return img

    def score(self, left: np.ndarray, right: np.ndarray, speed: float) -> dict[str, Any]:
        """The pair's JSON, as ``traffictwin risk`` prints it (no image paths: the request has
        none), with the speed checks' notes under ``warnings`` if there are any."""
        from traffictwin.io.jsonio import json_clean

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ApiWarning)  # returned as "warnings" below
            try:
                notes = check_speed(self.risk, speed)
            except ApiError as exc:
                raise RequestError(f"speed_mps: {str(exc).removeprefix('speed: ')}") from None
            (row,) = assess_risk(
                self.risk, [Frame(PAIR_ID, left, right)], speed=speed, settings=self.settings
            )
        out = {**row, **answered_by(self.risk, self.settings)}
        if notes:
            out["warnings"] = notes
        return json_clean(out)
