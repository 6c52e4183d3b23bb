"""Risk training: data loading over synthetic data/risk + data/disparity + orb.csv, Lightning fit.

``write_synthetic_risk`` (also used by test_risk_eval / test_risk_stages) writes small datasets in
the interface formats: one lead vehicle (a fronto-parallel box) at a known depth straight ahead,
ground plane disparity below the horizon, sky above; labels from the exact geometry.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from conftest import composed

from traffictwin.io.shards import DatasetError, DatasetWriter
from traffictwin.risk.dave2 import Dave2Config
from traffictwin.risk.metric import risk_from_time
from traffictwin.risk.training import RiskSource, TrainConfig, fit, prepare_split
from traffictwin.trainer import TrainerSettings

CAMERA = dict(width=96, height=48, baseline=0.16, mount_x=1.2, mount_height=1.3)
SUBJECT_LENGTH = 4.5


def camera_intrinsics(width: int = 96, height: int = 48, hfov_deg: float = 60.0) -> dict:
    fx = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
    return dict(
        CAMERA,
        width=width,
        height=height,
        fx=fx,
        fy=fx,
        cx=width / 2.0 - 0.5,
        cy=height / 2.0 - 0.5,
    )


def render_frame(
    cam: dict, depth: float | None, half_width: float = 0.9, height_m: float = 1.5, rng=None
):
    """GT disparity (H, W) px and a BGR image of a box whose rear face is ``depth`` m ahead of the camera."""
    H, W = cam["height"], cam["width"]
    v = np.arange(H, dtype=np.float64)[:, None] * np.ones((1, W))
    u = np.ones((H, 1)) * np.arange(W, dtype=np.float64)[None, :]
    disp = np.where(
        v > cam["cy"],
        cam["fx"] * cam["baseline"] * (v - cam["cy"]) / (cam["fy"] * cam["mount_height"]),
        0.0,
    )
    img = np.zeros((H, W, 3), np.float64)
    img[:] = (200, 170, 120)  # sky (BGR)
    img[v > cam["cy"]] = (90, 95, 100)  # road
    if depth is not None:
        Z = depth
        ulo, uhi = cam["cx"] - cam["fx"] * half_width / Z, cam["cx"] + cam["fx"] * half_width / Z
        vlo = cam["cy"] + cam["fy"] * (cam["mount_height"] - height_m) / Z
        vhi = cam["cy"] + cam["fy"] * cam["mount_height"] / Z
        box = (u >= ulo) & (u <= uhi) & (v >= vlo) & (v <= vhi)
        disp[box] = cam["fx"] * cam["baseline"] / Z
        img[box] = (40, 40, 190)
    if rng is not None:
        img += rng.normal(0, 4, img.shape)
    return disp.astype(np.float32), np.clip(img, 0, 255).astype(np.uint8)


def thw_risk(thw: np.ndarray) -> np.ndarray:
    return risk_from_time(thw)


def write_synthetic_risk(
    repo: Path,
    n_shards: int = 6,
    per_shard: int = 12,
    seed: int = 0,
    width: int = 96,
    height: int = 48,
    disp_shape: tuple[int, int] | None = None,
    outlier_rate: float = 0.1,
) -> pd.DataFrame:
    """data/risk, data/disparity and data/orb/orb.csv under ``repo``; returns frames.csv.

    Shards alternate splits: train for all but the last two, then val, then test.
    ``disp_shape`` (H, W): give the SGM disparity another size (bad input).
    """
    rng = np.random.default_rng(seed)
    cam = camera_intrinsics(width, height)
    rw = DatasetWriter(repo / "data" / "risk", "risk", {"synthetic": True}, seed)
    dw = DatasetWriter(repo / "data" / "disparity", "disparity", {"synthetic": True}, seed)
    rows, orb = [], []
    for s in range(n_shards):
        split = "test" if s == n_shards - 1 else "val" if s == n_shards - 2 else "train"
        lefts, gts, sgms = [], [], []
        for i in range(per_shard):
            speed = float(rng.uniform(5, 25))
            depth = float(rng.uniform(2.0, 35.0)) if rng.random() < 0.85 else None
            gt, left = render_frame(cam, depth, rng=rng)
            sgm = gt + rng.normal(0, 0.2, gt.shape).astype(np.float32)
            sgm[(gt <= 0) | (rng.random(gt.shape) < 0.1)] = -1.0
            if disp_shape is not None:
                sgm = np.full(disp_shape, -1.0, np.float32)
            dist = (depth + cam["mount_x"] - SUBJECT_LENGTH / 2) if depth is not None else np.inf
            thw = dist / speed
            r_fov = float(thw_risk(np.array(thw)))
            hidden = rng.random() < 0.2  # a vehicle beside the subject only the paper region sees
            r_paper = max(r_fov, float(thw_risk(np.array(1.0 / speed)))) if hidden else r_fov
            fid = s * per_shard + i
            rows.append(
                dict(
                    frame_id=fid,
                    shard=s,
                    idx=i,
                    scenario=s,
                    split=split,
                    t=0.1 * i,
                    speed=speed,
                    thw=thw,
                    risk=r_paper,
                    risk_thw_corridor=r_fov,  # the object straight ahead is in the corridor
                    risk_thw_paper=r_paper,
                    risk_thw_fov=r_fov,
                    risk_ttc=r_fov,
                    risk_wttc=r_fov,
                    fault="none",
                    depth=depth if depth is not None else np.inf,
                )
            )
            orb.append(
                dict(
                    frame_id=fid,
                    n_matches=100,
                    n_reliable=50,
                    mean_dx=5.0,
                    mean_dy=0.1,
                    outlier=bool(rng.random() < outlier_rate),
                )
            )
            lefts.append(left)
            gts.append(gt)
            sgms.append(sgm)
        rw.add_shard(
            s,
            {"left": np.stack(lefts), "right": np.stack(lefts), "disp_gt": np.stack(gts)},
            split=split,
        )
        dw.add_shard(s, {"disp_sgm": np.stack(sgms)}, split=split)
    frames = pd.DataFrame(rows)
    rw.add_table("frames.csv", frames)
    rw.finalize({"camera": cam})
    dw.finalize()
    (repo / "data" / "orb").mkdir(parents=True, exist_ok=True)
    pd.DataFrame(orb).to_csv(repo / "data" / "orb" / "orb.csv", index=False)
    return frames


def _source(repo: Path) -> RiskSource:
    return RiskSource(
        repo / "data" / "risk", repo / "data" / "disparity", repo / "data" / "orb" / "orb.csv"
    )


def test_source_drops_orb_outliers_and_keeps_splits(tmp_path: Path) -> None:
    frames = write_synthetic_risk(tmp_path)
    orb = pd.read_csv(tmp_path / "data" / "orb" / "orb.csv")
    src = _source(tmp_path)
    kept = set(orb.loc[~orb["outlier"], "frame_id"])
    assert set(src.frames["frame_id"]) == kept
    assert src.n_orb_outliers == int(orb["outlier"].sum()) > 0
    for split in ("train", "val", "test"):
        got = set(src.split_frames(split)["frame_id"])
        assert got == kept & set(frames.loc[frames["split"] == split, "frame_id"])


def test_prepare_split_shapes_and_values(tmp_path: Path) -> None:
    write_synthetic_risk(tmp_path)
    src = _source(tmp_path)
    cfg = Dave2Config(inputs=("rgb", "disp_sgm", "disp_gt"))
    a = prepare_split(src, cfg, "train", "risk_thw_paper")
    n = len(src.split_frames("train"))
    assert a.rgb.shape == (n, 3, 66, 200) and a.rgb.dtype == np.uint8
    assert a.disp.shape == (n, 2, 66, 200) and a.disp.dtype == np.float16
    assert float(a.disp.min()) >= 0.0  # invalid -1 mapped to 0
    assert np.all((a.y >= 0) & (a.y <= 1))
    sub = prepare_split(src, cfg, "train", "risk_thw_paper", max_frames=5, seed=1)
    assert len(sub) == 5 and set(sub.frame_id) <= set(a.frame_id)
    # the disparity-only config loads no image channels
    d = prepare_split(src, Dave2Config(inputs=("disp_sgm",)), "val", "risk_thw_fov")
    assert d.rgb.shape[1] == 0 and d.disp.shape[1] == 1


def test_mismatched_disparity_size_is_a_clear_error(tmp_path: Path) -> None:
    write_synthetic_risk(tmp_path, n_shards=3, per_shard=3, disp_shape=(40, 80))
    src = _source(tmp_path)
    with pytest.raises(DatasetError, match=r"sizes disagree.*disp_sgm"):
        prepare_split(src, Dave2Config(), "train", "risk_thw_paper")


def test_missing_orb_rows_and_label_column_are_errors(tmp_path: Path) -> None:
    write_synthetic_risk(tmp_path, n_shards=3, per_shard=3)
    orb = pd.read_csv(tmp_path / "data" / "orb" / "orb.csv")
    orb.iloc[:-1].to_csv(tmp_path / "data" / "orb" / "orb.csv", index=False)
    with pytest.raises(DatasetError, match="no ORB result for frame"):
        _source(tmp_path)
    orb.to_csv(tmp_path / "data" / "orb" / "orb.csv", index=False)
    with pytest.raises(DatasetError, match="label column 'nope' missing"):
        prepare_split(_source(tmp_path), Dave2Config(), "train", "nope")


@pytest.mark.integration
def test_fast_dev_run(tmp_path: Path) -> None:
    write_synthetic_risk(tmp_path, n_shards=3, per_shard=6)
    src = _source(tmp_path)
    cfg = Dave2Config(use_speed=True)
    tr, va = prepare_split(src, cfg, "train", "risk"), prepare_split(src, cfg, "val", "risk")
    res = fit(
        cfg,
        tr,
        va,
        TrainConfig(batch_size=4),
        TrainerSettings(),
        fast_dev_run=True,
    )
    assert res.steps == 1
    x = torch.zeros(2, 4, 66, 200)
    assert torch.isfinite(res.net(x, torch.tensor([10.0, 20.0]))).all()


@pytest.mark.integration
def test_overfit_few_batches_loss_falls(tmp_path: Path) -> None:
    """On 16 frames the training MSE must fall by a clear factor (the net can fit them)."""
    write_synthetic_risk(tmp_path, n_shards=3, per_shard=10, outlier_rate=0.0, seed=3)
    src = _source(tmp_path)
    cfg = Dave2Config()
    tr = prepare_split(src, cfg, "train", "risk_thw_fov", max_frames=16, seed=0)
    va = prepare_split(src, cfg, "val", "risk_thw_fov")
    tc = TrainConfig(epochs=40, batch_size=8, lr=1e-3, val_every_n_steps=1000, seed=0)
    from traffictwin.risk.dave2 import Dave2, normalise
    from traffictwin.trainer import seed_everything

    x = normalise(cfg, torch.from_numpy(tr.rgb), torch.from_numpy(tr.disp))
    seed_everything(
        tc.seed
    )  # fit() seeds the same way before building the net: same initial weights
    with torch.no_grad():
        initial = float(np.mean((Dave2(cfg)(x).numpy() - tr.y) ** 2))
    res = fit(cfg, tr, va, tc, TrainerSettings())
    with torch.no_grad():
        final = float(np.mean((res.net(x).numpy() - tr.y) ** 2))
    print(
        f"overfit: initial train MSE {initial:.5f}, final {final:.6f}, label variance {np.var(tr.y):.5f}"
    )
    assert final < initial / 10
    assert final < 0.2 * float(np.var(tr.y))
    assert len(res.history) >= 1 and np.isfinite(res.history["val/mse"]).all()


@pytest.mark.integration
def test_validation_every_n_steps_and_best_checkpoint(tmp_path: Path) -> None:
    write_synthetic_risk(tmp_path, n_shards=3, per_shard=10, outlier_rate=0.0)
    src = _source(tmp_path)
    cfg = Dave2Config(inputs=("disp_sgm",))
    tr, va = prepare_split(src, cfg, "train", "risk"), prepare_split(src, cfg, "val", "risk")
    # 12 steps on 20 synthetic frames: the spread guard is tested on its own below
    tc = TrainConfig(epochs=3, batch_size=5, lr=1e-3, val_every_n_steps=2, seed=0, min_pred_std=0.0)
    res = fit(cfg, tr, va, tc, TrainerSettings())
    steps_total = math.ceil(len(tr) / 5) * 3
    assert res.steps == steps_total
    assert list(res.history["step"]) == list(range(2, steps_total + 1, 2))
    assert res.best_val_mse == pytest.approx(res.history["val/mse"].min())
    # the returned weights are the best checkpoint's: their val MSE equals the best one
    from traffictwin.risk.dave2 import normalise

    with torch.no_grad():
        p = res.net(normalise(cfg, None, torch.from_numpy(va.disp))).numpy()
    assert float(np.mean((p - va.y) ** 2)) == pytest.approx(res.best_val_mse, rel=1e-4)


def _risk_model_node() -> dict:

    return composed()["risk_model"]


def test_risk_model_config_is_validated_once_with_full_keys() -> None:
    from traffictwin.config import ConfigError, typed
    from traffictwin.risk.training import RiskModelConfig

    node = _risk_model_node()
    m = typed(node, RiskModelConfig, key="risk_model")
    for name in m.run_variants:
        cfg, label = m.variant(name)
        v = node["variants"][name]
        assert cfg.inputs == tuple(v["inputs"]) and cfg.use_speed == v["speed"]
        assert label == (v["label"] or node["label"])
        assert (cfg.height, cfg.width, cfg.disp_scale) == (
            node["height"],
            node["width"],
            node["disp_scale"],
        )
    tc = m.train_config(seed=5)
    assert tc.seed == 5 + node["train"]["seed_offset"] and tc.epochs == node["train"]["epochs"]
    bad = [
        (("train", "epochs"), 0, "'risk_model.train.epochs' must be >= 1"),
        (("label",), "nope", "'risk_model.label' must be one of"),
        (("dropout",), 1.0, "'risk_model.dropout' must be <= 0.99"),
        (("run_variants",), ["rgbd", "zzz"], r"run_variants \['zzz'\] are not in variants"),
        (("train", "extra"), 1, "risk_model.train.extra"),
    ]
    for path, value, msg in bad:
        n = _risk_model_node()
        d = n
        for k in path[:-1]:
            d = d[k]
        d[path[-1]] = value
        with pytest.raises(ConfigError, match=msg):
            typed(n, RiskModelConfig, key="risk_model")
    n = _risk_model_node()
    n["train"]["limit_val_batches"] = 1.5
    with pytest.raises(ValueError, match="'train.limit_val_batches' must be a batch count"):
        typed(n, RiskModelConfig, key="risk_model").train_config(seed=0)
    n["train"]["limit_val_batches"] = 3
    assert typed(n, RiskModelConfig, key="risk_model").train_config(seed=0).limit_val_batches == 3
    n = _risk_model_node()
    n["variants"]["rgb"]["inputs"] = ["rgb", "x"]
    with pytest.raises(ValueError, match="unknown channel group"):
        typed(n, RiskModelConfig, key="risk_model").variant("rgb")
    n = _risk_model_node()
    del n["train"]["lr"]
    with pytest.raises(ConfigError, match="risk_model.train.lr"):
        typed(n, RiskModelConfig, key="risk_model")


def test_both_problems_share_one_trainer_shape() -> None:
    from traffictwin.fusion.losses import fusion_loss
    from traffictwin.fusion.training import FusionLitModule
    from traffictwin.risk.training import RiskRegressor, mse_loss
    from traffictwin.trainer import NetModule

    risk = RiskRegressor(Dave2Config(), lr=1e-3)
    spec = {
        "backbone": {"block": "basic", "layers": [1, 1, 1, 1], "base_width": 8},
        "aspp_channels": 8,
        "low_level_channels": 8,
        "decoder_channels": 8,
    }
    fusion = FusionLitModule(spec, {"lr": 0.02, "lr_factor": 0.25, "lr_patience": 3})
    assert isinstance(risk, NetModule) and isinstance(fusion, NetModule)
    assert risk.loss_fn is mse_loss and fusion.loss_fn is fusion_loss
    opt = risk.configure_optimizers()
    assert isinstance(opt, torch.optim.Adam) and opt.param_groups[0]["lr"] == 1e-3
    conf = fusion.configure_optimizers()
    sched = conf["lr_scheduler"]
    assert conf["optimizer"].param_groups[0]["lr"] == 0.02 and sched["monitor"] == "val/kld_full"
    assert (sched["scheduler"].factor, sched["scheduler"].patience) == (0.25, 3)
    # the optimiser holds exactly the injected network's parameters
    assert [id(p) for p in opt.param_groups[0]["params"]] == [id(p) for p in risk.net.parameters()]
    net = torch.nn.Linear(2, 1)
    custom = NetModule(net, torch.nn.functional.l1_loss, lr=0.1)
    assert custom.net is net and isinstance(custom.configure_optimizers(), torch.optim.Adam)


@pytest.mark.integration
def test_fit_risk_publishes_model_meta_and_curves(tmp_path: Path, mlflow_uri: str) -> None:
    import json

    import mlflow

    from traffictwin.risk.model_io import load_risk_model
    from traffictwin.risk.training import RiskVariant, fit_risk
    from traffictwin.trainer import TrackingSettings

    write_synthetic_risk(tmp_path, n_shards=3, per_shard=10, outlier_rate=0.0)
    cfg = Dave2Config(inputs=("disp_sgm",))
    tc = TrainConfig(epochs=2, batch_size=5, lr=1e-3, val_every_n_steps=2, seed=0, min_pred_std=0.0)
    out = tmp_path / "models" / "disp"
    (out / "stale.txt").parent.mkdir(parents=True)
    (out / "stale.txt").write_text("from an older run")
    res = fit_risk(
        _source(tmp_path),
        RiskVariant("disp", cfg, "risk", tc, meta={"domain": {"label": "risk"}}),
        TrainerSettings(),
        out_dir=out,
        curves_out=tmp_path / "plots" / "risk_training_disp.csv",
        tracking=TrackingSettings("risk", "risk-disp", profile="test", stage="train_risk@disp"),
    )
    assert res is not None and not (out / "stale.txt").exists()
    meta = json.loads((out / "model_meta.json").read_text())
    assert (meta["variant"], meta["label"], meta["domain"]) == ("disp", "risk", {"label": "risk"})
    assert meta["best_val_mse"] == res.best_val_mse and res.model_uri.startswith("models:/")
    # run id, model URI and timing only in the result (the stage's run record), never in the model
    assert not {"mlflow_run_id", "mlflow_model_uri", "train_seconds"} & set(meta)
    # the MLflow model is the same weights + meta, loaded without unpickling code
    from traffictwin.mlops.registry import load_registered

    logged = load_registered(res.model_uri, load_risk_model)
    local = load_risk_model(out)
    assert logged.cfg == local.cfg and logged.meta["domain"] == {"label": "risk"}
    for (k, a), b in zip(
        local.net.state_dict().items(), logged.net.state_dict().values(), strict=True
    ):
        assert torch.equal(a, b), k
    curves = (tmp_path / "plots" / "risk_training_disp.csv").read_text()
    assert curves == (out / "history.csv").read_text()
    assert curves.splitlines()[0] == "step,epoch,train/loss,val/loss,val/mse,val/mae,val/pred_std"
    loaded = load_risk_model(out)
    assert all(torch.equal(v, res.net.state_dict()[k]) for k, v in loaded.net.state_dict().items())
    run = mlflow.get_run(res.run_id)
    assert run.data.metrics["val/best_mse"] == pytest.approx(res.best_val_mse)
    assert run.data.params["data.n_train"] == str(res.n_train)
    hist = mlflow.MlflowClient().get_metric_history(run.info.run_id, "val/mse")
    assert [m.step for m in hist] == list(res.history["step"])


# ---- collapse guard, objectives, replicates -----------------------------------------------------


def test_check_spread_flags_a_constant_net(tmp_path: Path) -> None:
    from traffictwin.risk.dave2 import Dave2
    from traffictwin.risk.training import CollapsedModelError, check_spread

    write_synthetic_risk(tmp_path, n_shards=3, per_shard=10, outlier_rate=0.0)
    cfg = Dave2Config(inputs=("disp_sgm",))
    va = prepare_split(_source(tmp_path), cfg, "val", "risk")
    torch.manual_seed(0)
    net = Dave2(cfg).eval()
    with torch.no_grad():  # last layer: no weights, bias 0.2 -> the same risk for every frame
        net.head[-1].weight.zero_()
        net.head[-1].bias.fill_(0.2)
    with pytest.raises(CollapsedModelError, match=r"collapsed: .* spread by 0\.00e\+00"):
        check_spread(net, va, cfg)
    with torch.no_grad():  # a head that passes one feature through: the outputs differ
        net.head[-1].weight.fill_(0.5)
    assert check_spread(net, va, cfg, min_std=0.0) >= 0.0


@pytest.mark.integration
def test_collapsed_run_publishes_nothing(tmp_path: Path) -> None:
    from traffictwin.risk.training import CollapsedModelError, RiskVariant, fit_risk

    write_synthetic_risk(tmp_path, n_shards=3, per_shard=10, outlier_rate=0.0)
    out = tmp_path / "models" / "disp"
    out.mkdir(parents=True)
    (out / "model.ckpt").write_text("the good model of an earlier run")
    tc = TrainConfig(epochs=1, batch_size=5, val_every_n_steps=2, seed=0, min_pred_std=1e9)
    with pytest.raises(CollapsedModelError):
        fit_risk(
            _source(tmp_path),
            RiskVariant("disp", Dave2Config(inputs=("disp_sgm",)), "risk", tc),
            TrainerSettings(),
            out_dir=out,
        )
    assert (out / "model.ckpt").read_text() == "the good model of an earlier run"
    assert sorted(p.name for p in out.iterdir()) == ["model.ckpt"]


def test_objective_losses_hand_values() -> None:
    from traffictwin.risk.dave2 import raw_to_risk, risk_loss, risk_to_log_thw

    y = torch.tensor([0.0, 1 / 30, 0.5])  # nothing ahead, THW 1.5 s, THW 0.1 s
    mse = Dave2Config(objective="mse")
    raw = torch.tensor([[0.1], [0.0], [0.5]])
    assert float(risk_loss(mse, raw, y)) == pytest.approx((0.01 + (1 / 30) ** 2) / 3)
    assert torch.allclose(raw_to_risk(mse, torch.tensor([[-0.2], [1.3]])), torch.tensor([0.0, 1.0]))

    lt = Dave2Config(objective="log_thw", thw_cap_s=10.0)
    target = risk_to_log_thw(lt, y)
    assert torch.allclose(target, torch.log(torch.tensor([10.0, 1.5, 0.1])))
    assert float(risk_loss(lt, target[:, None], y)) == pytest.approx(0.0, abs=1e-10)
    back = raw_to_risk(lt, target[:, None])
    assert torch.allclose(back, torch.tensor([0.0, 1 / 30, 0.5]), atol=1e-6)  # cap -> 0

    cls = Dave2Config(objective="mse_bce", critical_thw_s=1.5)
    raw2 = torch.tensor([[0.0, 0.0], [1 / 30, 0.0], [0.5, 0.0]])  # perfect regression, logit 0
    # y = 1/30 is exactly at the threshold: not critical (THW < 1.5 s is critical)
    assert float(risk_loss(cls, raw2, y, bce_weight=0.5)) == pytest.approx(0.5 * np.log(2))


def test_objective_needs_matching_outputs_and_valid_name() -> None:
    from traffictwin.risk.dave2 import Dave2

    assert Dave2(Dave2Config(objective="mse_bce", critical_thw_s=1.5)).head[-1].out_features == 2
    assert Dave2(Dave2Config(objective="log_thw")).head[-1].out_features == 1
    with pytest.raises(ValueError, match="objective must be one of"):
        Dave2Config(objective="hinge")


def test_replicates_must_match_their_base_and_differ_in_seed() -> None:
    from traffictwin.config import ConfigError, typed
    from traffictwin.risk.training import RiskModelConfig

    node = _risk_model_node()
    m = typed(node, RiskModelConfig, key="risk_model")
    base = m.train_config(7, "headline").seed
    assert m.train_config(7, "headline_s1").seed == base + 1
    assert m.train_config(7, "headline_s2").seed == base + 2
    bad = _risk_model_node()
    bad["variants"]["headline_s1"]["seed_offset"] = 0
    with pytest.raises(ConfigError, match="another seed_offset"):
        typed(bad, RiskModelConfig, key="risk_model")
    bad = _risk_model_node()
    bad["variants"]["headline_s1"]["speed"] = False
    with pytest.raises(ConfigError, match=r"differs in \['speed'\]"):
        typed(bad, RiskModelConfig, key="risk_model")


def test_learning_rate_warms_up_linearly() -> None:
    from traffictwin.risk.training import RiskRegressor

    m = RiskRegressor(Dave2Config(inputs=("disp_sgm",)), lr=1e-3, warmup_steps=4)
    conf = m.configure_optimizers()
    opt, sched = conf["optimizer"], conf["lr_scheduler"]["scheduler"]
    assert conf["lr_scheduler"]["interval"] == "step"
    lrs = []
    for _ in range(6):
        lrs.append(opt.param_groups[0]["lr"])
        opt.step()
        sched.step()
    np.testing.assert_allclose(lrs, [2.5e-4, 5e-4, 7.5e-4, 1e-3, 1e-3, 1e-3])
    plain = RiskRegressor(Dave2Config(inputs=("disp_sgm",)), lr=1e-3).configure_optimizers()
    assert isinstance(plain, torch.optim.Adam)
