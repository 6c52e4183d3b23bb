"""The learned stereo network in the registry (``traffictwin-stereo``): with tracking, training
logs it sealed (weights + JSON, no pickle) with a signature and a validation pair as input
example; the gate registers it, scores it on fixed validation pairs, and its pyfunc serves the
packed pair (checked like every served model). On a tiny trained network."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from test_stereo_learned_stages import SGM, TRAIN, _risk

from pipelines import disparity as disparity_stage
from pipelines import promote as pm
from pipelines._paths import PARAMS, metrics_file
from traffictwin.config import load_params
from traffictwin.mlops import model_artifact as art
from traffictwin.mlops import promotion
from traffictwin.mlops import registry as reg
from traffictwin.mlops.gate import Gate
from traffictwin.risk.stereo_gate import (
    load_registered_stereo,
    stereo_evaluator,
    stereo_scores,
    stereo_test_set,
)
from traffictwin.risk.stereo_inference import learned_disparity
from traffictwin.risk.stereo_training import (
    StereoData,
    fit_stereo,
    load_stereo_model,
    pack_pairs,
)
from traffictwin.stereo.network import StereoNetSpec
from traffictwin.trainer import ModelOutputs, TrackingSettings, TrainerSettings


def test_promote_gates_the_stereo_network_on_validation_pairs() -> None:
    cfg = load_params(PARAMS)
    rc = pm.registry_config(cfg)
    jobs = {j.name: j for j in pm.build_jobs(cfg, rc)}
    job = jobs["traffictwin-stereo"]
    assert rc.stereo.name == reg.STEREO_NAME == "traffictwin-stereo"
    assert job.model_dir == pm.STEREO_MODEL and job.tags == {"model_dir": "models/stereo/learned"}
    assert job.record_path.name == "train_stereo.json"
    assert job.gate == Gate("val/epe", "min", rc.stereo.margin) and rc.stereo.split == "val"
    assert "traffictwin-stereo" in pm.model_names(cfg, rc)
    meta = {"image_size": [160, 320], "architecture": {"base": "sgm"}}
    card = job.card(promotion.Candidate(job.name, "r", None, job.model_dir, meta))
    stereo = json.loads(metrics_file("stereo").read_text())
    assert card.metrics["learned/own/epe"] == stereo["learned/own/epe"]
    assert "320 x 160 px" in card.limits[1] and "data/disparity" in card.data


def test_stereo_scores_hand_case() -> None:
    gt = np.array([[[2.0, 3.0, 0.0, 4.0]]], np.float32)
    d = np.array([[[2.5, 1.0, 9.0, -1.0]]], np.float32)  # 0.5 and 2 px; no GT; invalid
    s = stereo_scores(d, gt, "val")
    assert s == {"val/epe": 1.25, "val/bad1": 0.5, "val/density": pytest.approx(2 / 3)}


def test_trained_stereo_network_is_logged_registered_gated_and_served(
    tmp_path: Path, mlflow_uri: str, monkeypatch
) -> None:
    import mlflow

    monkeypatch.chdir(tmp_path)
    cl = reg.client(mlflow_uri)
    _risk(tmp_path / "risk")
    disparity_stage.run(
        SGM, 1, [0.0, 10.0, 30.0, 90.0], src=tmp_path / "risk", out=tmp_path / "disp"
    )
    spec = StereoNetSpec(
        base="sgm", refine_channels=4, refine_dilations=(1,), refine_stride=1, max_residual_px=1.0
    )
    model = tmp_path / "model"
    res = fit_stereo(
        StereoData(tmp_path / "risk", 0, tmp_path / "disp"),
        spec=spec,
        train=TRAIN,
        trainer_settings=TrainerSettings(accelerator="cpu", devices=1, precision="32-true"),
        outputs=ModelOutputs(model / "model.ckpt", model / "model_meta.json", tmp_path / "m.json"),
        tracking=TrackingSettings("stereo", "stereo", profile="test", stage="train_stereo"),
    )
    assert res is not None and res.model_uri
    mv = reg.ensure_version(cl, reg.STEREO_NAME, res.run_id)
    assert art.SHA_TAG in mv.tags
    local = load_stereo_model(model)
    logged = load_registered_stereo(reg.version_uri(reg.STEREO_NAME, 1))
    for (k, a), b in zip(local.state_dict().items(), logged.state_dict().values(), strict=True):
        assert torch.equal(a, b), k

    # users load it by reference through the same sealed path (API and CLI)
    from traffictwin import api

    cl.set_registered_model_alias(reg.STEREO_NAME, "champion", mv.version)
    by_ref = api.load_stereo("traffictwin-stereo@champion", tracking_uri=mlflow_uri)
    assert "traffictwin-stereo@champion" in by_ref.description and by_ref.source == "learned"
    with pytest.raises(api.ApiError, match="is not a stereo model"):
        api.load_stereo("traffictwin-risk@champion", tracking_uri=mlflow_uri)

    # the gate's score of the registered version is the local network's on the same pairs
    data, fp = stereo_test_set(tmp_path / "risk", tmp_path / "disp", "val", 2)
    assert fp.startswith("stereo:") and fp.endswith(":val:2")
    got = stereo_evaluator(data, 2, "val")(reg.version_uri(reg.STEREO_NAME, 1))
    disp, _ = learned_disparity(local, data["left"], data["right"], sgm=data["disp_sgm"])
    assert got == stereo_scores(disp, data["disp_gt"], "val") and np.isfinite(got["val/epe"])

    # the pyfunc: a signature, an input example, and the packed pair's disparity served
    info = mlflow.models.get_model_info(res.model_uri)
    assert info.signature is not None and info.saved_input_example_info is not None
    x = pack_pairs(data["left"][:1], data["right"][:1], data["disp_sgm"][:1])
    pyfunc = mlflow.pyfunc.load_model(res.model_uri)
    y = pyfunc.predict(x)
    assert y.shape == (1, 2, *x.shape[2:])
    np.testing.assert_allclose(y[:, 0], disp[:1], atol=1e-5)
    from mlflow.exceptions import MlflowException

    bad = x.copy()
    bad[0, 0, 0, 0] = 300.0
    with pytest.raises(MlflowException, match="expected 8-bit"):
        pyfunc.predict(bad)
    # the model's own shape check names the training size (MLflow's schema check comes first)
    from mlflow.artifacts import download_artifacts

    from traffictwin.mlops import serving

    served = serving._load_pyfunc(download_artifacts(res.model_uri, dst_path=str(tmp_path / "dl")))
    with pytest.raises(MlflowException, match=r"\(N, 7, 64, 128\).*training images"):
        served.predict(x[:, :, :-4])
