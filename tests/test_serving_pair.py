"""The serving app's ``POST /risk`` answers a stereo pair (two base64 PNGs and the speed) with
what ``traffictwin risk`` prints for the same files, refuses bad requests with HTTP 400 naming
the field, and leaves ``/invocations`` as MLflow serves it.

The model is the ``ci`` profile's shipped risk model without running the DAG: its validation
split holds too few critical frames to choose a predictor on, so ``select_risk`` ships the
corridor rule on SGM disparity at half-width 1.75 m (README, Quick start) — built here from the
``ci`` composition (camera, SGM / ORB settings, speed range, rule settings) and the sample
pair's camera intrinsics, logged as ``select_risk`` logs it and registered as
``traffictwin-risk@champion`` in a temp SQLite store. Requests go in-process to the ASGI app.
"""

from __future__ import annotations

import base64
import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch
from _asgi import asgi_call
from conftest import composed

from traffictwin import api, cli
from traffictwin.mlops import model_artifact as art
from traffictwin.mlops import registry as reg
from traffictwin.mlops import serving_app
from traffictwin.risk.config import GeometricConfig
from traffictwin.risk.model_io import CKPT, META, save_predictor
from traffictwin.risk.predictors import GeometricRiskModel, PackedPredictor
from traffictwin.risk.selection_suite import CAMERA_KEYS

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "risk"
LEFT, RIGHT = EXAMPLE / "000_left.png", EXAMPLE / "000_right.png"
SPEED = json.loads((EXAMPLE / "000.json").read_text())["speed_m_s"]
NAME = "traffictwin-risk"
URI = f"models:/{NAME}@champion"
#: the ci profile's shipped corridor half-width (m)
CI_HALF_WIDTH = 1.75
#: fields that differ between two runs on the same pair (ms timings) or name the input files
VOLATILE = {"orb_ms", "sgm_ms", "model_ms", "id", "left", "right"}


def ci_shipped_rule(folder: Path) -> Path:
    """The ci profile's shipped corridor rule, saved as ``select_risk`` saves it."""
    c = composed("profile=ci")
    rd, metric = c["risk_data"], c["risk_data"]["metric"]
    g = c["evaluation"]["risk"]["geometric"]
    geo = GeometricConfig(**{k: g[k] for k in GeometricConfig.__dataclass_fields__})
    camera = json.loads((EXAMPLE / "000.json").read_text())["camera"]
    assert (camera["width"], camera["height"]) == (rd["camera"]["width"], rd["camera"]["height"])
    rule = GeometricRiskModel(
        geo.params(metric["subject_length"], metric["subject_width"], CI_HALF_WIDTH),
        {k: float(camera[k]) for k in CAMERA_KEYS},
    )
    domain = {
        "camera": {"width": rd["camera"]["width"], "height": rd["camera"]["height"]},
        "max_speed": float(rd["max_speed"]),
        "sgm": dict(rd["sgm"]),
        "orb": dict(rd["orb"]),
    }
    meta = {"variant": "shipped", "objective": "rule", "label": "corridor", "domain": domain}
    return save_predictor(rule, folder, meta)


def register_champion(folder: Path) -> None:
    """Log the rule in folder as ``select_risk`` logs it (pyfunc of the packed input) and make it
    ``traffictwin-risk@champion`` of the current tracking URI."""
    import mlflow
    from mlflow.models import infer_signature

    from traffictwin.risk.model_io import load_risk_model

    model = load_risk_model(folder)
    h, w = int(model.camera["height"]), int(model.camera["width"])
    x = np.full((1, 1 + h * w), -1.0, np.float32)
    x[:, 0] = SPEED
    with torch.no_grad():
        y = PackedPredictor(model)(torch.from_numpy(x)).numpy()
    mlflow.set_experiment("risk")
    with mlflow.start_run(run_name="risk-shipped") as run:
        art.log_model(
            {art.CKPT: folder / CKPT, art.META: folder / META},
            problem="risk",
            signature=infer_signature(x, y),
            input_example=x,
        )
    cl = reg.client(mlflow.get_tracking_uri())
    mv = reg.ensure_version(cl, NAME, run.info.run_id)
    cl.set_registered_model_alias(NAME, "champion", mv.version)


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[object, Path]]:
    """The bounded app of ``traffictwin-risk@champion`` (the ci shipped rule) and its folder."""
    from conftest import mlflow_uris_kept
    from mlflow.environment_variables import _MLFLOW_IS_IN_SERVING_ENVIRONMENT

    tmp = tmp_path_factory.mktemp("serving_pair")
    mp = pytest.MonkeyPatch()
    with mlflow_uris_kept():
        mp.chdir(tmp)  # MLflow's artifacts (./mlruns) go to the temp folder
        mp.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp / 'mlflow.db'}")
        mp.setenv("TRAFFICTWIN_MODEL_CACHE", str(tmp / "model_cache"))
        mp.setenv(_MLFLOW_IS_IN_SERVING_ENVIRONMENT.name, "false")  # init sets it; restored after
        mp.delenv(serving_app.ENV_MAX_BYTES, raising=False)
        try:
            folder = ci_shipped_rule(tmp / "risk_shipped")
            register_champion(folder)
            yield serving_app.build(URI), folder
        finally:
            mp.undo()


call = asgi_call  # (status, JSON body) of a request to the app


def b64(path_or_bytes: Path | bytes) -> str:
    data = path_or_bytes if isinstance(path_or_bytes, bytes) else path_or_bytes.read_bytes()
    return base64.b64encode(data).decode()


def pair_request(**fields) -> bytes:
    req = {"left_png": b64(LEFT), "right_png": b64(RIGHT), "speed_mps": SPEED}
    req.update(fields)
    return json.dumps({k: v for k, v in req.items() if v is not ...}).encode()


def test_risk_answers_what_the_cli_prints_for_the_same_files(served, capsys):
    app, _ = served
    status, got = call(app, serving_app.RISK_PATH, pair_request())
    assert status == 200, got
    # the CLI on the same files and the same registered model
    rc = cli.main(["risk", str(LEFT), str(RIGHT), "--speed", str(SPEED), "--model", URI])
    assert rc == 0
    want = json.loads(capsys.readouterr().out)
    assert {k: v for k, v in got.items() if k not in VOLATILE} == {
        k: v for k, v in want.items() if k not in VOLATILE
    }
    assert set(want) - set(got) == {"left", "right"}  # the request holds no file names
    # the sample is a critical cut-in (its labels) and the pair passes its check
    assert got["verdict"] == "critical" and got["critical"] is True and got["thw_s"] < 1.5
    assert got["orb_verdict"] == "ok" and got["speed_m_s"] == SPEED
    assert got["predictor"].startswith("geometric") and got["model"].startswith(NAME)
    # and the API called directly on the decoded images
    risk = api.load_risk(URI)
    (row,) = api.assess_risk(risk, [api.Frame("pair", LEFT, RIGHT)], speed=SPEED)
    for k in ("risk", "thw_s", "gap_m", "verdict", "orb_n_reliable", "disp_valid_fraction"):
        assert got[k] == row[k], k


def _png_bytes(img: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", img)
    assert ok
    return buf.tobytes()


def bad_requests() -> dict[str, tuple[bytes, tuple[str, ...]]]:
    """case -> (request body, what the 400 message must say)."""
    import cv2

    left = cv2.imread(str(LEFT), cv2.IMREAD_UNCHANGED)
    small = _png_bytes(cv2.resize(left, (160, 80)))
    jpeg = cv2.imencode(".jpg", left)[1].tobytes()
    truncated = LEFT.read_bytes()[:2000]
    return {
        "not json": (b"{left_png: 1", ("request body", "not valid JSON")),
        "not an object": (b"[1, 2]", ("request body", "expected a JSON object")),
        "missing left": (pair_request(left_png=...), ("left_png: missing",)),
        "missing speed": (pair_request(speed_mps=...), ("speed_mps: missing",)),
        "unknown field": (pair_request(speed=3.0), ("unknown field(s) ['speed']",)),
        "bad base64": (pair_request(right_png="not*base64!"), ("right_png", "not valid base64")),
        "number for an image": (pair_request(left_png=7), ("left_png", "expected a string")),
        "not a png": (pair_request(left_png=b64(jpeg)), ("left_png", "not a PNG")),
        "undecodable png": (pair_request(right_png=b64(truncated)), ("right_png", "decodable")),
        "wrong size": (
            pair_request(right_png=b64(small)),
            ("right_png", "160x80", "camera 320x160"),
        ),
        "negative speed": (pair_request(speed_mps=-1.0), ("speed_mps", ">= 0", "-1.0")),
        "infinite speed": (
            b'{"speed_mps": Infinity, "left_png": "", "right_png": ""}',
            ("speed_mps", "finite"),
        ),
        "nan speed": (pair_request(speed_mps=float("nan")), ("speed_mps", "finite")),
        "speed as text": (pair_request(speed_mps="8"), ("speed_mps", "expected a number")),
        "bool speed": (pair_request(speed_mps=True), ("speed_mps", "expected a number")),
        "beyond the training range": (
            pair_request(speed_mps=40.0),
            ("speed_mps", "outside the model's training range", "[0, 25]"),
        ),
        "nested too deep": (b'{"left_png": ' + b"[" * 40 + b"]" * 40 + b"}", ("nested 41",)),
    }


def test_bad_requests_get_400_naming_the_field(served):
    app, _ = served
    for case, (body, needles) in bad_requests().items():
        status, got = call(app, serving_app.RISK_PATH, body)
        assert status == 400, (case, status, got)
        msg = got["message"]
        assert got["error_code"] == "INVALID_PARAMETER_VALUE" and "\n" not in msg, (case, got)
        for n in needles:
            assert n in msg, (case, n, msg)


def test_body_limit_fits_two_camera_pngs_and_refuses_more(served, monkeypatch):
    app, _ = served
    limit = serving_app.risk_request_bytes(320, 160)
    # two worst-case (incompressible RGBA) PNGs of the camera's size fit
    noise = np.random.default_rng(0).integers(0, 256, (160, 320, 4), dtype=np.uint8)
    worst = pair_request(left_png=b64(_png_bytes(noise)), right_png=b64(_png_bytes(noise)))
    assert len(worst) < limit
    status, got = call(app, serving_app.RISK_PATH, b" " * (limit + 1))
    assert status == 413 and f"more than the limit of {limit}" in got["message"], got
    # the server's explicit limit holds for /risk too
    monkeypatch.setenv(serving_app.ENV_MAX_BYTES, "1000")
    assert serving_app.risk_request_bytes(320, 160) == 1000


def test_invocations_still_serve_the_tensor_signature(served):
    app, folder = served
    from traffictwin.risk.model_io import load_risk_model

    model = load_risk_model(folder)
    x = np.full((2, 1 + 160 * 320), -1.0, np.float32)
    x[:, 0] = SPEED
    with torch.no_grad():
        want = PackedPredictor(model)(torch.from_numpy(x)).numpy()
    status, got = call(app, "/invocations", json.dumps({"inputs": x.tolist()}).encode())
    assert status == 200, got
    np.testing.assert_allclose(got["predictions"], want, rtol=1e-6)
    # MLflow's own checks and the bounds before parsing are unchanged
    status, got = call(app, "/invocations", b'{"inputs": [[true]]}')
    assert status == 400 and "true/false" in got["message"], got
    status, got = call(app, "/invocations", json.dumps({"inputs": x[:, :5].tolist()}).encode())
    assert status == 400, got


def test_risk_on_another_models_app_is_404_in_one_line():
    async def mlflow_app(scope, receive, send):  # stands for MLflow's app: never reached
        raise AssertionError("MLflow's app got /risk")

    routes = serving_app.model_routes("models:/traffictwin-fusion@champion", "fusion", 1 << 20)
    app = serving_app.bounded(mlflow_app, 1 << 20, routes=routes)
    status, got = call(app, serving_app.RISK_PATH, pair_request())
    assert status == 404, got
    msg = got["message"]
    assert "\n" not in msg and "/risk" in msg and "a fusion model" in msg and "risk model" in msg


def test_a_stereo_model_is_passed_to_the_api_loader(served, monkeypatch):
    """``TRAFFICTWIN_SERVE_STEREO_MODEL`` reaches :func:`traffictwin.api.load_risk` as
    ``stereo_model``: the ci rule reads SGM's disparity, so giving one makes ``/risk`` answer 404
    with the loader's reason (and ``/invocations`` would still serve)."""
    from traffictwin.api import serving as pair_serving

    monkeypatch.setenv(pair_serving.ENV_STEREO_MODEL, str(ROOT / "examples"))
    status, got = pair_serving.pair_route(URI).answer(pair_request())
    assert status == 404, got
    assert "stereo_model" in got["message"] and "disp_sgm" in got["message"], got
    monkeypatch.delenv(pair_serving.ENV_STEREO_MODEL)
    status, got = pair_serving.pair_route(URI).answer(pair_request())
    assert status == 200 and got["verdict"] == "critical", got
