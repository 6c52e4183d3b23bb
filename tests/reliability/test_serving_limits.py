"""The pyfunc model behind ``mlflow models serve``
refuses NaN, implausible values and oversized batches (HTTP 400 with a one-line reason) and never
answers NaN.

Tiny models (a DAVE-2 with the speed input on 8 x 8 px, the CLI tests' small fusion network, the
corridor rule on a 16 x 8 px camera) are wrapped directly in
:class:`traffictwin.mlops.serving.TrafficTwinModel`, and one is saved as an MLflow model
directory and served in-process through MLflow's scoring server app (ASGI, no socket).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from _asgi import asgi_call
from _cli_models import save_fusion_model

from traffictwin.mlops import serving
from traffictwin.risk.dave2 import Dave2, Dave2Config
from traffictwin.risk.model_io import save_risk_model

SPEED_RANGE = [0.0, 25.0]  # m/s, the risk model's training domain
TINY = {"height": 8, "width": 8, "conv": ((4, 3, 1),), "fc": (4,), "use_speed": True}


def _risk_input(n: int = 2, speed: float = 10.0, seed: int = 0) -> np.ndarray:
    """(n, 5, 8, 8) float32: normalised RGB in [-1, 1], disparity / scale in [0, 1], speed plane."""
    g = np.random.default_rng(seed)
    x = np.empty((n, 5, 8, 8), np.float32)
    x[:, :3] = g.uniform(-1, 1, (n, 3, 8, 8))
    x[:, 3] = g.uniform(0, 1, (n, 8, 8))
    x[:, 4] = speed
    return x


@pytest.fixture(scope="module")
def risk_folder(tmp_path_factory) -> Path:
    torch.manual_seed(0)
    net = Dave2(Dave2Config(**TINY)).eval()
    meta = {"label": "risk", "domain": {"speed_range": SPEED_RANGE}}
    return save_risk_model(net, tmp_path_factory.mktemp("risk") / "m", meta)


@pytest.fixture(scope="module")
def risk_model(risk_folder) -> serving.TrafficTwinModel:
    net, meta = serving._load("risk", risk_folder)
    return serving.TrafficTwinModel(net, "risk", meta)


def _refused(model, x, *needles: str, params=None, status: int = 400) -> str:
    from mlflow.exceptions import MlflowException

    with pytest.raises(MlflowException) as info:
        model.predict(x, params)
    msg = info.value.message
    assert info.value.get_http_status_code() == status, msg
    assert "\n" not in msg, msg
    for n in needles:
        assert n in msg, msg
    return msg


# ------------------------------------------------------------------ the wrapper, called directly


def test_plausible_input_is_answered_with_finite_numbers(risk_model):
    y = risk_model.predict(_risk_input(3))
    assert y.shape == (3,) and y.dtype == np.float32 and np.isfinite(y).all()


@pytest.mark.parametrize(
    ("case", "needles"),
    [
        ("nan", ("NaN/inf", "index (1, 0, 2, 3)")),
        ("inf", ("NaN/inf",)),
        ("beyond_float32", ("NaN/inf", "beyond float32")),
        ("huge", ("channel 'r'", "1e+30")),
        ("negative_speed", ("speed -1000 m/s", "[0, 25]", "domain.speed_range")),
        ("too_fast", ("speed 40 m/s",)),
        ("uneven_speed_plane", ("speed plane", "not constant")),
        ("wrong_shape", ("expected shape (N, 5, 8, 8)",)),
        ("not_numeric", ("expected a float32 array",)),
    ],
)
def test_implausible_input_is_refused_with_400(risk_model, case, needles):
    x = _risk_input(2)
    if case == "nan":
        x[1, 0, 2, 3] = np.nan
    elif case == "inf":
        x[0, 3, 0, 0] = np.inf
    elif case == "beyond_float32":
        x = x.astype(np.float64)
        x[0, 1, 1, 1] = 1e300
    elif case == "huge":
        x[:, :4] = 1e30
    elif case == "negative_speed":
        x[1, 4] = -1000.0
    elif case == "too_fast":
        x[0, 4] = 40.0
    elif case == "uneven_speed_plane":
        x[0, 4, 3, 3] = 11.0
    elif case == "wrong_shape":
        x = x[:, :, :, :7]
    else:
        x = np.array([["a"] * 4] * 2)
    _refused(risk_model, x, "risk model input", *needles)


def test_batch_limit_default_environment_and_params(risk_model, monkeypatch):
    monkeypatch.delenv(serving.ENV_MAX_BATCH, raising=False)
    x = _risk_input(serving.MAX_BATCH + 1)
    _refused(
        risk_model, x, f"batch of {serving.MAX_BATCH + 1} samples", f"limit of {serving.MAX_BATCH}"
    )
    assert risk_model.predict(x[: serving.MAX_BATCH]).shape == (serving.MAX_BATCH,)
    monkeypatch.setenv(serving.ENV_MAX_BATCH, "2")
    _refused(risk_model, x[:3], "batch of 3 samples", "limit of 2", serving.ENV_MAX_BATCH)
    # a request may lower the limit, never raise it
    _refused(risk_model, x[:2], "limit of 1", params={"max_batch": 1})
    _refused(risk_model, x[:3], "limit of 2", params={"max_batch": 1000})
    _refused(risk_model, x[:1], "params.max_batch", params={"max_batch": 0})
    monkeypatch.setenv(serving.ENV_MAX_BATCH, "lots")
    _refused(risk_model, x[:1], serving.ENV_MAX_BATCH, "positive integer", status=500)


def test_fusion_masses_must_be_on_the_simplex_and_on_the_training_grid(tmp_path):
    net, meta = serving._load("fusion", save_fusion_model(tmp_path / "f"))
    model = serving.TrafficTwinModel(net, "fusion", meta)
    rows, cols = int(meta["grid"]["rows"]), int(meta["grid"]["cols"])
    x = np.full((2, 4, rows, cols), 0.25, np.float32)
    y = model.predict(x)
    assert y.shape == (2, 2, rows, cols) and np.isfinite(y).all()
    bad = x.copy()
    bad[1, 2, 5, 6] = 1.5
    _refused(model, bad, "outside [0, 1]", "sample 1, map 2, row 5, col 6")
    bad = x.copy()
    bad[0, 0, 0, 0], bad[0, 1, 0, 0] = 0.7, 0.7  # each in [0, 1], together > 1
    _refused(model, bad, "simplex", "max m_F + m_O 1.4")
    _refused(model, x * np.float32(1e30), "outside [0, 1]")
    _refused(model, x[:, :, :16], f"expected shape (N, 4, {rows}, {cols})")


@pytest.mark.filterwarnings("ignore:invalid value:RuntimeWarning")  # the rule on invalid pixels
def test_corridor_rule_input_speed_and_disparity_are_checked():
    from traffictwin.risk.baselines import GeometricParams
    from traffictwin.risk.predictors import GeometricRiskModel, PackedPredictor

    camera = {
        "fx": 20.0,
        "fy": 20.0,
        "cx": 8.0,
        "cy": 4.0,
        "baseline": 0.5,
        "mount_x": 1.0,
        "mount_height": 1.4,
        "width": 16,
        "height": 8,
    }
    rule = GeometricRiskModel(GeometricParams(), camera, {"domain": {"max_speed": 20.0}})
    model = serving.TrafficTwinModel(PackedPredictor(rule), "risk")  # meta: the predictor's
    x = np.full((2, 1 + 8 * 16), -1.0, np.float32)  # every pixel invalid
    x[:, 0] = 10.0
    assert np.isfinite(model.predict(x)).all()
    bad = x.copy()
    bad[1, 5] = -7.0
    _refused(model, bad, "SGM disparity -7 px at sample 1", "[-1, 16] px")
    bad = x.copy()
    bad[0, 0] = -1000.0
    _refused(model, bad, "speed -1000 m/s", "[0, 20]", "domain.max_speed")
    _refused(model, x[:, :-1], "expected shape (N, 129)")


def test_a_non_finite_output_is_never_returned():
    def nan_net(x: torch.Tensor) -> torch.Tensor:
        return torch.full((len(x), 2, *x.shape[2:]), float("nan"))

    model = serving.TrafficTwinModel(nan_net, "registration", {})
    _refused(model, np.zeros((1, 4, 16, 16), np.float32), "model output", "NaN/inf", status=500)


# ------------------------------------------------------------------ through MLflow's scoring server


def _post(app, payload: dict | bytes) -> tuple[int, dict]:
    """POST ``payload`` as JSON (or raw bytes) to ``/invocations`` of the ASGI ``app``; (status,
    JSON body)."""
    # NaN is written as the literal NaN, as clients do
    body = payload if isinstance(payload, bytes) else json.dumps(payload).encode()
    return asgi_call(app, "/invocations", body)


@pytest.fixture(scope="module")
def served(risk_folder, tmp_path_factory):
    """MLflow's scoring server app for the tiny risk model saved as an MLflow model directory."""
    import mlflow.pyfunc
    from mlflow.environment_variables import _MLFLOW_IS_IN_SERVING_ENVIRONMENT
    from mlflow.models import Model, infer_signature
    from mlflow.pyfunc import scoring_server

    from traffictwin.mlops import model_artifact as art

    example = _risk_input(2)
    with torch.no_grad():
        net = serving._load("risk", risk_folder)[0]
        out = net(torch.from_numpy(example)).numpy()
    folder = tmp_path_factory.mktemp("served") / "model"
    art.save_model(
        str(folder),
        Model(),
        files={art.CKPT: risk_folder / art.CKPT, art.META: risk_folder / art.META},
        problem="risk",
        signature=infer_signature(example, out),
        input_example=example,
    )
    mp = pytest.MonkeyPatch()
    mp.setenv(_MLFLOW_IS_IN_SERVING_ENVIRONMENT.name, "false")  # init sets it; restored after
    try:
        yield scoring_server.init(mlflow.pyfunc.load_model(str(folder)))
    finally:
        mp.undo()


def test_scoring_server_answers_400_to_nan_speed_and_batch(served, monkeypatch):
    monkeypatch.setenv(serving.ENV_MAX_BATCH, "2")
    status, body = _post(served, {"inputs": _risk_input(2).tolist()})
    assert status == 200, body
    assert len(body["predictions"]) == 2 and all(np.isfinite(body["predictions"]))

    nan = _risk_input(1)
    nan[0, 1, 2, 3] = np.nan
    fast = _risk_input(1, speed=-1000.0)
    cases = {
        "NaN": (nan, "NaN/inf"),
        "speed": (fast, "speed -1000 m/s"),
        "batch": (_risk_input(3), "batch of 3 samples"),
        "huge": (_risk_input(1) * np.float32(1e30), "beyond"),
    }
    for case, (x, needle) in cases.items():
        status, body = _post(served, {"inputs": x.tolist()})
        assert status == 400, (case, status, body)
        assert body["error_code"] == "INVALID_PARAMETER_VALUE", (case, body)
        assert needle in body["message"] and "risk model input" in body["message"], (case, body)


# ------------------------------------------------------------------ params, bools, bounds before parsing


def test_request_params_max_batch_is_honoured_and_checked(served):
    x = _risk_input(2).tolist()
    status, body = _post(served, {"inputs": x, "params": {"max_batch": 1}})
    assert status == 400 and "batch of 2 samples, more than the limit of 1" in body["message"]
    status, body = _post(served, {"inputs": x, "params": {"max_batch": 2}})
    assert status == 200 and len(body["predictions"]) == 2
    for bad in (True, 1.5, "3"):
        status, body = _post(served, {"inputs": x, "params": {"max_batch": bad}})
        assert status == 400, (bad, body)
        assert "max_batch" in body["message"], (bad, body)


def test_bools_are_not_numbers(risk_model, served):
    from traffictwin.mlops import serving_app

    x = _risk_input(1) > 0
    _refused(risk_model, x, "expected a float32 array, got dtype bool")
    # MLflow's own server casts them to 1.0 / 0.0 by the signature before predict (documented);
    # the bounded app refuses them before parsing
    x = _risk_input(1).tolist()
    x[0][0][0][0] = True
    status, body = _post(serving_app.bounded(served, 1 << 20), {"inputs": x})
    assert status == 400 and "true/false" in body["message"], body


def test_bounded_app_refuses_size_and_nesting_before_parsing(served, monkeypatch):
    import json as _json

    from traffictwin.mlops import serving_app

    calls = []

    async def spy(scope, receive, send):
        calls.append(scope["path"])
        await served(scope, receive, send)

    ok = {"inputs": _risk_input(2).tolist()}
    limit = len(_json.dumps(ok).encode()) + 10
    app = serving_app.bounded(spy, limit)
    status, body = _post(app, ok)
    assert status == 200 and len(body["predictions"]) == 2 and calls == ["/invocations"]

    status, body = _post(app, {"inputs": _risk_input(3).tolist()})  # bigger than the limit
    assert status == 413 and f"more than the limit of {limit}" in body["message"], body
    deep = b'{"inputs": ' + b"[" * 3000 + b"1" + b"]" * 3000 + b"}"
    status, body = _post(serving_app.bounded(spy, 1 << 20), deep)
    assert status == 400 and "nested 3001 levels deep" in body["message"], body
    assert "\n" not in body["message"]
    assert calls == ["/invocations"]  # neither reached MLflow's parser

    # the limit follows the signature: max_batch samples of 5 x 8 x 8 values
    monkeypatch.setenv(serving.ENV_MAX_BATCH, "2")
    assert serving_app.max_request_bytes(320) == 2 * 320 * 16 + (1 << 20)
    monkeypatch.setenv(serving_app.ENV_MAX_BYTES, "true")
    with pytest.raises(ValueError, match="TRAFFICTWIN_SERVE_MAX_BYTES"):
        serving_app.max_request_bytes(320)
    assert serving_app.nesting_depth(b'{"a": [[1], [2]]}') == 3
