"""The disparity a user gets: ``traffictwin risk`` (API, CLI) computes the disparity the risk
model reads, the learned stereo network's for a model trained on it (loaded from its own sealed
folder, given or packaged with the risk model), after the same pair check; ``traffictwin
disparity`` writes a pair's disparity and confidence from SGM or the learned network. On a tiny
trained network and rendered pairs."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest
from test_stereo_learned_stages import SGM, SPEC, TRAIN, _risk

from pipelines import disparity as disparity_stage
from traffictwin import api, cli
from traffictwin.io.shards import Dataset
from traffictwin.risk.baselines import GeometricParams
from traffictwin.risk.model_io import save_predictor
from traffictwin.risk.predictors import GeometricRiskModel, PredictorInputs
from traffictwin.risk.stereo_inference import learned_disparity
from traffictwin.risk.stereo_training import StereoData, fit_stereo, load_stereo_model
from traffictwin.stereo.network import StereoNetSpec
from traffictwin.stereo.sgm import compute_disparity
from traffictwin.trainer import ModelOutputs, TrainerSettings

SGM_SETTINGS = {"num_disparities": SGM.num_disparities, "block_size": SGM.block_size}
SPEED = 12.0


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A tiny trained ``base: sgm`` stereo network, rule models on the learned and on SGM's
    disparity, and a rendered pair as PNG files."""
    root = tmp_path_factory.mktemp("disparity_sources")
    _risk(root / "risk")
    disparity_stage.run(SGM, 1, [0.0, 10.0, 30.0, 90.0], src=root / "risk", out=root / "disparity")
    spec = StereoNetSpec(
        base="sgm", refine_channels=4, refine_dilations=(1,), refine_stride=1, max_residual_px=1.0
    )
    stereo = root / "stereo"
    fit_stereo(
        StereoData(root / "risk", 0, root / "disparity"),
        spec=spec,
        train=TRAIN,
        trainer_settings=TrainerSettings(accelerator="cpu", devices=1, precision="32-true"),
        outputs=ModelOutputs(stereo / "model.ckpt", stereo / "model_meta.json", root / "m.json"),
    )
    cam = SPEC.camera.intrinsics()
    geo = GeometricParams(corridor_half_width=1.0)
    domain = {
        "camera": {"width": int(cam["width"]), "height": int(cam["height"])},
        "sgm": SGM_SETTINGS,
        "max_speed": 30.0,
    }
    rules = {}
    for key in ("disp_learned", "disp_sgm"):
        rule = GeometricRiskModel(geo, dict(cam), cfg=PredictorInputs((key,)))
        rules[key] = save_predictor(rule, root / key, {"domain": domain})
    shard = Dataset(root / "risk", kind="risk").load_shard(0)
    left, right = shard["left"][1], shard["right"][1]
    cv2.imwrite(str(root / "f_left.png"), left)
    cv2.imwrite(str(root / "f_right.png"), right)
    return {"root": root, "stereo": stereo, "rules": rules, "left": left, "right": right}


def _expected(setup: dict) -> tuple[np.ndarray, np.ndarray, float]:
    """SGM's and the network's disparity of the pair, and the rule's risk on the learned one."""
    left, right = setup["left"], setup["right"]
    sgm = compute_disparity(left, right, **SGM_SETTINGS)
    net = load_stereo_model(setup["stereo"])
    disp, _ = learned_disparity(net, left[None], right[None], sgm=sgm[None])
    rule = api.load_risk(setup["rules"]["disp_learned"], stereo_model=setup["stereo"]).model
    risk = rule.predict(disparity={"disp_learned": disp}, speed=np.array([SPEED]))[0]
    return sgm, disp[0], float(risk)


def test_risk_computes_the_learned_disparity_its_model_reads(setup: dict, capsys) -> None:
    root, stereo = setup["root"], setup["stereo"]
    learned_rule, sgm_rule = setup["rules"]["disp_learned"], setup["rules"]["disp_sgm"]
    sgm, disp, want = _expected(setup)
    assert np.array_equal(disp < 0, sgm < 0) and np.abs(disp - sgm).max() > 0  # it refines SGM
    with pytest.raises(api.ModelDomainError, match="stereo-model models/stereo/learned"):
        api.load_risk(learned_rule)
    with pytest.raises(api.InputValueError, match="reads the disparity 'disp_sgm'"):
        api.load_risk(sgm_rule, stereo_model=stereo)

    risk = api.load_risk(learned_rule, stereo_model=stereo)
    frame = api.Frame("f", root / "f_left.png", root / "f_right.png")
    (row,) = api.assess_risk(risk, [frame], speed=SPEED)
    assert row["disp_source"] == "disp_learned" and row["orb_verdict"] == "ok"
    assert row["risk"] == pytest.approx(want, abs=1e-7)
    assert row["disp_median_px"] == pytest.approx(float(np.median(disp[disp >= 0])))

    # the network packaged in the risk model's folder is found there
    packaged = root / "packaged"
    shutil.copytree(learned_rule, packaged)
    shutil.copytree(stereo, packaged / api.PACKAGED_STEREO)
    (row2,) = api.assess_risk(api.load_risk(packaged), [frame], speed=SPEED)
    assert row2["risk"] == row["risk"]

    # the CLI: the same risk, the network named in the output
    argv = ["risk", str(root / "f_left.png"), str(root / "f_right.png"), "--speed", str(SPEED)]
    assert cli.main([*argv, "--model", str(learned_rule), "--stereo-model", str(stereo)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["risk"] == pytest.approx(want, abs=1e-7) and "stereo" in out["stereo_model"]
    # a broken pair (cameras swapped) is still refused a verdict before the network is trusted
    swapped = ["risk", str(root / "f_right.png"), str(root / "f_left.png"), "--speed", "12"]
    assert cli.main([*swapped, "--model", str(packaged)]) == 3
    assert json.loads(capsys.readouterr().out)["verdict"] == api.UNKNOWN


def test_disparity_command_writes_the_map_and_its_confidence(setup: dict, capsys) -> None:
    root, stereo = setup["root"], setup["stereo"]
    sgm, disp, _ = _expected(setup)
    pair = [str(root / "f_left.png"), str(root / "f_right.png")]
    params = root / "params.yaml"
    params.write_text(json.dumps({"risk_data": {"sgm": SGM_SETTINGS}}))
    out = root / "learned.npz"
    argv = ["disparity", *pair, "--params", str(params), "-o", str(out)]
    assert cli.main([*argv, "--model", str(stereo)]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["source"] == "learned" and summary["orb_verdict"] == "ok"
    with np.load(out) as z:
        assert z["disparity"].dtype == np.float32 and z["disparity"].shape == sgm.shape
        np.testing.assert_array_equal(z["disparity"], disp)
        conf = z["confidence"]
    assert conf.min() >= 0 and conf.max() <= 1 and np.all(conf[disp < 0] == 0)
    assert conf[disp >= 0].mean() > 0

    sgm_out = root / "sgm.npz"
    assert cli.main(["disparity", *pair, "--params", str(params), "-o", str(sgm_out)]) == 0
    with np.load(sgm_out) as z:
        np.testing.assert_array_equal(z["disparity"], sgm)
        np.testing.assert_array_equal(z["confidence"], (sgm >= 0).astype(np.float32))
    capsys.readouterr()

    # the output rule: an existing output only with --force, and only a disparity .npz
    assert cli.main([*argv, "--model", str(stereo)]) == 1
    assert "--force" in capsys.readouterr().err
    assert cli.main([*argv, "--model", str(stereo), "--force"]) == 0
    np.savez(root / "other.npz", m_free=np.zeros(2), m_occ=np.zeros(2), u=np.ones(2))
    other = ["disparity", *pair, "-o", str(root / "other.npz"), "--force"]
    assert cli.main(other) == 1
    assert "disparity .npz" in capsys.readouterr().err
    # the input checks of risk: a missing image, images of different sizes, the network's size
    assert cli.main(["disparity", pair[0], str(root / "nope.png"), "-o", str(root / "x.npz")]) == 1
    assert "image not found" in capsys.readouterr().err
    cv2.imwrite(str(root / "small.png"), cv2.resize(setup["right"], (64, 32)))
    assert cli.main(["disparity", pair[0], str(root / "small.png"), "-o", str(root / "x.npz")]) == 1
    assert "differs" in capsys.readouterr().err
    cv2.imwrite(str(root / "small_l.png"), cv2.resize(setup["left"], (64, 32)))
    small = [str(root / "small_l.png"), str(root / "small.png")]
    assert cli.main(["disparity", *small, "--model", str(stereo), "-o", str(root / "x.npz")]) == 1
    assert "stereo network's training images" in capsys.readouterr().err
    assert not (root / "x.npz").exists()
