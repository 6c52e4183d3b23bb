"""Choices on validation (decision cuts, corridor widths, the shipped predictor), the
corridor rule / hybrid as predictors, seeds in the intervals, the median THW error."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from _acceptance import thresholds
from test_risk_eval_stats import write_sequences
from test_risk_training import SUBJECT_LENGTH, camera_intrinsics

from traffictwin.risk.baselines import (
    GeometricParams,
    corridor_distances,
    geometric_distance,
    lateral_bin_distances,
    thw_from_distance,
)
from traffictwin.risk.evaluation import (
    TARGET_NAMES,
    CIConfig,
    ClusterBootstrap,
    Holdout,
    SuiteSettings,
    bootstrap_scores,
    classification_metrics,
    evaluate_suite,
    mean_of_scores,
    seed_draws,
    weighted_median_stat,
)
from traffictwin.risk.model_io import RiskModelError, load_risk_model, save_predictor
from traffictwin.risk.predictor import RiskFrames
from traffictwin.risk.predictors import (
    GeometricRiskModel,
    HybridConfig,
    HybridRiskModel,
    PredictorInputs,
    corridor_features,
    fit_hybrid,
    log_thw_target,
)
from traffictwin.risk.selection import (
    balanced_accuracy,
    best_cut,
    choose,
    too_few,
    tune_half_width,
)
from traffictwin.risk.training import RiskSource

RISK = thresholds("risk")  # acceptance.risk

CAM = camera_intrinsics(96, 48)


def _wall(depth_m: float, lateral: tuple[float, float], h: int = 48, w: int = 96) -> np.ndarray:
    """Disparity (1, H, W) of a vertical wall ``depth_m`` ahead of the camera spanning lateral
    offsets ``lateral`` (m, vehicle frame, left +) over every row at obstacle height."""
    fx, cx, b = CAM["fx"], CAM["cx"], CAM["baseline"]
    d = np.full((1, h, w), -1.0, np.float32)
    u = np.arange(w)
    y = b / 2 - (u - cx) * depth_m / fx  # lateral offset of each column at that depth
    cols = (y >= lateral[0]) & (y <= lateral[1])
    d[0][:, cols] = fx * b / depth_m
    return d


# --------------------------------------------------------------------------- geometry


def test_corridor_distances_one_pass_equals_the_single_band_rule() -> None:
    p = GeometricParams(
        min_height=-10.0, max_height=10.0, min_pixels=3, subject_length=SUBJECT_LENGTH
    )
    disp = np.concatenate([_wall(10.0, (0.6, 1.4)), _wall(20.0, (-0.3, 0.3))])
    d = corridor_distances(disp, CAM, p, [0.5, 1.0, 2.0])
    for k, w in enumerate([0.5, 1.0, 2.0]):
        single = geometric_distance(
            disp, CAM, GeometricParams(**{**p.__dict__, "corridor_half_width": w})
        )
        np.testing.assert_allclose(d[:, k], single)
    # frame 0: the wall at 0.6..1.4 m to the left is outside the 0.5 m band, inside 1.0 and 2.0
    assert np.isinf(d[0, 0]) and np.isfinite(d[0, 1])
    # the free distance from the bumper: depth + mount_x - length/2 (the wall reaches the corridor
    # 0.6 m to the side; the bumper's half-width 0.9 m covers it: no lateral gap)
    assert d[0, 1] == pytest.approx(10.0 + CAM["mount_x"] - SUBJECT_LENGTH / 2, abs=0.05)
    # frame 1: straight ahead, every band sees it
    assert np.all(np.isfinite(d[1]))
    with pytest.raises(ValueError, match="half-widths"):
        corridor_distances(disp, CAM, p, [])


def test_lateral_bins_put_an_obstacle_in_its_strip() -> None:
    p = GeometricParams(
        min_height=-10.0, max_height=10.0, min_pixels=3, subject_length=SUBJECT_LENGTH
    )
    d = lateral_bin_distances(_wall(12.0, (1.1, 1.4)), CAM, p, [-2.0, -1.0, 0.0, 1.0, 2.0])
    assert d.shape == (1, 4)
    assert np.isinf(d[0, :3]).all() and np.isfinite(d[0, 3])  # only the 1..2 m (left) strip
    with pytest.raises(ValueError, match="increasing"):
        lateral_bin_distances(_wall(12.0, (1.1, 1.4)), CAM, p, [1.0, 0.0])


def test_thw_from_distance_broadcasts_and_handles_standstill() -> None:
    t = thw_from_distance(np.array([[10.0, np.inf], [5.0, 2.0]]), np.array([5.0, 0.0]))
    assert t[0, 0] == pytest.approx(2.0) and np.isinf(t[0, 1]) and np.isinf(t[1]).all()


# --------------------------------------------------------------------------- selection


def test_best_cut_maximises_balanced_accuracy_by_hand() -> None:
    pos = np.array([1, 1, 0, 0, 0], bool)
    score = np.array([0.9, 0.4, 0.5, 0.1, 0.2])
    # cut between 0.4 and 0.2 (0.3): TPR 1, TNR 2/3 -> 0.8333; cut 0.45: TPR 1/2, TNR 2/3 -> 0.583;
    # cut 0.7: TPR 1/2, TNR 1 -> 0.75
    cut, ba = best_cut(pos, score, default=1 / 30)
    assert cut == pytest.approx(0.3) and ba == pytest.approx((1 + 2 / 3) / 2)
    assert balanced_accuracy(pos, score > cut) == pytest.approx(ba)
    # one class only: the default, BA undefined
    c, b = best_cut(np.zeros(3, bool), np.array([0.1, 0.2, 0.3]), default=0.05)
    assert c == 0.05 and np.isnan(b)
    with pytest.raises(ValueError, match="finite"):
        best_cut(pos, np.array([0.1, np.nan, 0.2, 0.3, 0.4]), 0.05)


def test_best_cut_tie_goes_to_the_cut_nearest_the_label_threshold() -> None:
    pos = np.array([1, 0], bool)
    cut, ba = best_cut(pos, np.array([0.9, 0.1]), default=0.8)
    assert ba == 1.0 and cut == pytest.approx(0.5)  # the only perfect cut lies between them


def test_tune_half_width_picks_the_best_validation_auc() -> None:
    speed = np.full(4, 10.0)
    pos = np.array([1, 1, 0, 0], bool)
    # band 0: ranks the frames wrong; band 1: perfectly
    d = np.array([[40.0, 5.0], [40.0, 6.0], [5.0, 60.0], [6.0, np.inf]])
    w, table = tune_half_width(d, speed, pos, [0.5, 1.0], threshold_s=1.5, min_class=2)
    assert w == 1.0
    assert table[0]["roc_auc"] == pytest.approx(0.0) and table[1]["roc_auc"] == pytest.approx(1.0)
    assert table[1]["balanced_accuracy"] == pytest.approx(1.0)  # THW 0.5 / 0.6 s < 1.5 s


def test_choose_prefers_auc_then_the_simpler_kind() -> None:
    c = {
        "net": {"roc_auc": 0.90, "kind": "dave2"},
        "hyb": {"roc_auc": 0.95, "kind": "hybrid"},
        "rule": {"roc_auc": 0.95, "kind": "geometric"},
    }
    assert choose(c) == "rule"
    c["hyb"]["roc_auc"] = 0.951
    assert choose(c) == "hyb"
    with pytest.raises(ValueError):
        choose({})


def test_choose_never_picks_a_nan_score() -> None:
    c = {"rule": {"roc_auc": float("nan"), "kind": "geometric"}, "net": {"roc_auc": 0.6}}
    assert choose(c) == "net"
    with pytest.raises(ValueError, match="finite"):
        choose({"rule": {"roc_auc": float("nan"), "kind": "geometric"}})


def test_tune_half_width_falls_back_to_the_prior_with_too_few_positives() -> None:
    """Validation that cannot rank the bands (one critical frame) keeps the prior width, not
    the narrowest band."""
    speed = np.full(12, 10.0)
    pos = np.zeros(12, bool)
    pos[0] = True
    d = np.tile([40.0, 5.0], (12, 1))
    assert too_few(pos) == "not enough validation positives (n=1 critical of 12 frames, 5 needed)"
    assert too_few(~pos).startswith("not enough validation negatives (n=1")
    w, table = tune_half_width(d, speed, pos, [0.5, 1.0], threshold_s=1.5, prior=1.75)
    assert w == 1.75 and len(table) == 2
    with pytest.raises(ValueError, match="not enough validation positives"):
        tune_half_width(d, speed, pos, [0.5, 1.0], threshold_s=1.5)


# --------------------------------------------------------------------------- statistics


def test_decision_cut_changes_only_the_classification() -> None:
    y = np.array([0.1, 0.05, 0.0, 0.0])  # critical at 1.5 s: risk > 1/30 -> frames 0, 1
    p = np.array([0.03, 0.02, 0.01, 0.0])  # squeezed predictions: nothing above 1/30
    base = classification_metrics(y, p, 1.5)
    assert base["recall"] == 0.0 and base["decision_cut"] == pytest.approx(1 / 30)
    cut = classification_metrics(y, p, 1.5, cut=0.015)
    assert cut["recall"] == 1.0 and cut["specificity"] == 1.0 and cut["roc_auc"] == base["roc_auc"]
    plan = ClusterBootstrap(np.arange(4), n_boot=50, seed=0)
    sc = bootstrap_scores(y, p, plan, (1.5,), cuts={1.5: 0.015})
    assert sc["at_1.5s|balanced_accuracy"][0] == pytest.approx(1.0)


def test_weighted_median_stat_matches_numpy_and_resamples() -> None:
    v = np.array([3.0, 1.0, 2.0, 10.0, 0.5])
    mask = np.array([1, 1, 1, 1, 0], bool)
    plan = ClusterBootstrap(np.array([0, 0, 1, 2, 2]), n_boot=200, seed=1)
    est, boot = weighted_median_stat(v, mask, plan)
    assert est == pytest.approx(np.median(v[mask]))
    # each resample's value is one of the masked values (a lower weighted median)
    assert set(np.unique(boot)) <= set(v[mask])
    # a resample drawing only sequence 2 (value 10): median 10
    only = ClusterBootstrap(np.array([0, 0, 1, 2, 2]), n_boot=1, seed=0)
    only.draws = np.array([[0.0, 0.0, 3.0]])
    assert weighted_median_stat(v, mask, only)[1][0] == 10.0


def test_seed_resampling_widens_the_seed_mean_interval() -> None:
    plan = ClusterBootstrap(np.arange(20), n_boot=500, seed=0)
    rng = np.random.default_rng(0)
    runs = [{"m": (mu, mu + rng.normal(0, 0.01, 500))} for mu in (0.6, 0.7, 0.8)]
    plain = mean_of_scores(runs)["m"]
    crossed = mean_of_scores(runs, seed_draws(3, plan))["m"]
    assert plain[0] == crossed[0] == pytest.approx(0.7)
    assert np.std(crossed[1]) > 3 * np.std(plain[1])  # seed-to-seed spread is in the interval
    d = seed_draws(3, plan)
    assert d.shape == (500, 3) and np.all(d.sum(axis=1) == 3)
    np.testing.assert_array_equal(d, seed_draws(3, plan))  # deterministic


def test_test_mse_is_no_target() -> None:
    assert "test_mse" not in TARGET_NAMES and "test_mse" not in RISK
    assert {"shipped_balanced_accuracy_primary", "learned_vs_rule_auc"} <= set(TARGET_NAMES)


# --------------------------------------------------------------------------- predictors


def test_rule_and_hybrid_round_trip_through_the_model_folder(tmp_path: Path) -> None:
    p = GeometricParams(corridor_half_width=1.0, min_height=-10, max_height=10, min_pixels=3)
    rule = GeometricRiskModel(
        p, {**{k: float(v) for k, v in CAM.items()}, "width": 96.0, "height": 48.0}
    )
    disp = np.concatenate([_wall(8.0, (-0.5, 0.5)), _wall(8.0, (1.5, 2.0))])
    speed = np.array([10.0, 10.0])
    r = rule.predict(disp_sgm=disp, speed=speed)
    assert r[0] > 0 and r[1] == 0  # the wall beside the 1 m corridor is no obstacle
    save_predictor(rule, tmp_path / "rule", {"label": "risk_thw_corridor"})
    back = load_risk_model(tmp_path / "rule")
    np.testing.assert_allclose(back.predict(disp_sgm=disp, speed=speed), r)
    assert back.meta["label"] == "risk_thw_corridor" and back.cfg.use_speed

    cfg = HybridConfig(half_widths=(0.5, 1.0), bin_edges=(-1.0, 0.0, 1.0), epochs=3, hidden=8)
    x = corridor_features(disp, speed, rule.camera, p, cfg)
    assert x.shape == (2, cfg.n_features) and np.all(np.isfinite(x))
    assert x[0, 0] == pytest.approx(10.0 / cfg.speed_scale)
    net, hist = fit_hybrid(np.repeat(x, 8, 0), np.repeat([0.8, np.inf], 8), cfg, seed=3)
    net2, _ = fit_hybrid(np.repeat(x, 8, 0), np.repeat([0.8, np.inf], 8), cfg, seed=3)
    for a, b in zip(net.state_dict().values(), net2.state_dict().values()):
        assert torch_equal(a, b)  # deterministic for a seed
    assert len(hist) == 3 and np.isfinite(hist[-1]["train_loss"])
    hyb = HybridRiskModel(net, cfg, p, rule.camera, {"label": "risk_thw_corridor"})
    save_predictor(hyb, tmp_path / "hyb")
    hb = load_risk_model(tmp_path / "hyb")
    np.testing.assert_allclose(
        hb.predict(disp_sgm=disp, speed=speed), hyb.predict(disp_sgm=disp, speed=speed)
    )
    # a replaced checkpoint is refused (the meta records the checkpoint's hash)
    (tmp_path / "hyb" / "model.ckpt").write_bytes((tmp_path / "rule" / "model.ckpt").read_bytes())
    with pytest.raises(RiskModelError, match="not one pair"):
        load_risk_model(tmp_path / "hyb")


def test_predictors_read_the_disparity_they_name_from_frames_given_by_key(tmp_path: Path) -> None:
    """Callers hand every disparity by key; each predictor takes its own (a rule built for the
    learned disparity keeps that key through its model folder), and hybrids of one feature setting
    share one corridor profile per frames object."""
    p = GeometricParams(corridor_half_width=1.0, min_height=-10, max_height=10, min_pixels=3)
    cam = {**{k: float(v) for k, v in CAM.items()}, "width": 96.0, "height": 48.0}
    near, none = _wall(8.0, (-0.5, 0.5)), _wall(8.0, (1.5, 2.0))
    speed = np.array([10.0])
    frames = RiskFrames(disparity={"disp_sgm": none, "disp_learned": near}, speed=speed)
    sgm_rule = GeometricRiskModel(p, cam)
    learned_rule = GeometricRiskModel(p, cam, cfg=PredictorInputs(("disp_learned",)))
    assert sgm_rule.predict_frames(frames, 8)[0] == 0
    assert learned_rule.predict_frames(frames, 8)[0] > 0
    assert "disparity" not in sgm_rule.architecture()  # SGM's rule keeps its checkpoint layout
    save_predictor(learned_rule, tmp_path / "rule")
    back = load_risk_model(tmp_path / "rule")
    assert back.cfg.inputs == ("disp_learned",)
    assert back.predict(disparity={"disp_learned": near}, speed=speed)[0] > 0
    with pytest.raises(
        ValueError, match="reads the disparity 'disp_learned'.*given: \\['disp_sgm'\\]"
    ):
        back.predict(disp_sgm=near, speed=speed)

    cfg = HybridConfig(half_widths=(0.5, 1.0), bin_edges=(-1.0, 0.0, 1.0), epochs=2, hidden=8)
    x = corridor_features(np.concatenate([near, none]), np.array([10.0, 10.0]), cam, p, cfg)
    hybrids = [
        HybridRiskModel(fit_hybrid(x, np.array([0.8, np.inf]), cfg, seed=s)[0], cfg, p, cam)
        for s in (0, 1)
    ]
    two = RiskFrames(
        disparity={"disp_sgm": np.concatenate([near, none])}, speed=np.array([10.0, 10.0])
    )
    preds = [h.predict_frames(two, 8) for h in hybrids]
    assert len(two.derived) == 1  # one profile for both seeds
    for h, pr in zip(hybrids, preds):
        np.testing.assert_array_equal(pr, h.predict_features(x))
    with pytest.raises(ValueError, match="unknown key"):
        RiskFrames(disparity={"disp_mono": near})


def torch_equal(a, b) -> bool:
    import torch

    return bool(torch.equal(a, b))


def test_log_thw_target_caps_nothing_ahead() -> None:
    t = log_thw_target(np.array([np.inf, np.nan, 0.01, 2.0]), cap=10.0)
    np.testing.assert_allclose(np.exp(t), [10.0, 10.0, 0.05, 2.0], rtol=1e-6)


def test_fit_hybrid_refuses_bad_features() -> None:
    cfg = HybridConfig(half_widths=(1.0,), bin_edges=(-1.0, 1.0), epochs=1)
    with pytest.raises(ValueError, match="expected"):
        fit_hybrid(np.zeros((4, 2), np.float32), np.ones(4), cfg, 0)
    with pytest.raises(ValueError, match="'epochs'"):
        HybridConfig(epochs=0)


# --------------------------------------------------------------------------- the suite


def test_suite_applies_validation_choices(tmp_path: Path) -> None:
    """The rule's tuned corridor, every predictor's decision cut and the shipped predictor reach
    the test metrics; the shipped one is judged by the targets."""
    write_sequences(tmp_path, n_shards=4, per_shard=18)
    src = RiskSource(tmp_path / "data" / "risk", tmp_path / "data" / "disparity", None)
    geo = GeometricParams(subject_length=SUBJECT_LENGTH, subject_width=1.8)
    cam = {
        k: float(v)
        for k, v in src.camera.items()
        if k in ("fx", "fy", "cx", "cy", "baseline", "mount_x", "mount_height", "width", "height")
    }
    narrow = GeometricParams(**{**geo.__dict__, "corridor_half_width": 0.75})
    rule = GeometricRiskModel(narrow, cam, {"label": "risk_thw_corridor"})
    settings = SuiteSettings(
        acceptance=RISK,
        thresholds_s=(1.5, 1.0),
        primary_label="risk_thw_corridor",
        geometric=geo,
        ci=CIConfig(100, 0, 0.95),
        rule_params={"geometric_sgm": narrow},
        decisions={"shipped": {1.5: 0.02, 1.0: 0.04}},
        shipped="shipped",
    )
    metrics, pred = evaluate_suite(src, {"shipped": rule}, settings)
    json.dumps(metrics, allow_nan=False)
    # the shipped rule = the SGM baseline with the same corridor
    np.testing.assert_allclose(pred["pred_shipped"], pred["pred_geometric_sgm"], rtol=1e-6)
    assert metrics["baselines"]["geometric_sgm"]["params"]["corridor_half_width"] == 0.75
    assert metrics["baselines"]["geometric_gt"]["params"]["corridor_half_width"] == 2.0
    m = metrics["models"]["shipped"]
    assert m["at_1.5s"]["decision_cut"] == pytest.approx(0.02)
    y = pred["risk_thw_corridor"].to_numpy()
    p = pred["pred_shipped"].to_numpy()
    want = classification_metrics(y, p, 1.5, cut=0.02)["balanced_accuracy"]
    assert m["at_1.5s"]["balanced_accuracy"] == pytest.approx(want)
    t = metrics["targets"]
    assert t["shipped_balanced_accuracy_1.5s"]["predictor"] == "shipped"
    assert t["shipped_balanced_accuracy_1.5s"]["value"] == pytest.approx(want)
    assert metrics["decisions"]["shipped"]["1.5"] == 0.02
    crit = y > 1 / 30
    from traffictwin.risk.metric import risk_to_thw

    med = float(np.median(np.abs(risk_to_thw(p) - risk_to_thw(y))[crit]))
    assert m["test/thw_median_error_critical_s"] == pytest.approx(med)


def test_holm_adjusts_by_hand_and_bootstrap_p() -> None:
    from traffictwin.risk.evaluation import bootstrap_p, holm

    adj = holm({"a": 0.01, "b": 0.04, "c": 0.03, "d": float("nan")})
    # sorted 0.01, 0.03, 0.04 of m = 3: 0.03, max(0.03, 0.06) = 0.06, max(0.06, 0.04) = 0.06
    assert adj == pytest.approx({"a": 0.03, "c": 0.06, "b": 0.06})
    assert bootstrap_p(np.array([1.0, 2.0, 3.0, -1.0])) == pytest.approx(0.5)
    assert bootstrap_p(np.array([1.0, 2.0])) == 0.0 and np.isnan(bootstrap_p(np.array([np.nan])))


def test_holdout_block_measures_unseen_templates(tmp_path: Path) -> None:
    """Runs trained without some road templates, scored on those templates' test frames, against
    the reference trained on every template (here: the same predictions, so the gap is the
    template subset's own difficulty)."""
    import pandas as pd

    write_sequences(tmp_path, n_shards=4, per_shard=18)
    f = tmp_path / "data" / "risk" / "frames.csv"
    frames = pd.read_csv(f)
    frames["template"] = np.where(frames["scenario"] % 2 == 0, "roundabout", "straight")
    frames.to_csv(f, index=False)
    from traffictwin.io.shards import sha256_file

    man = tmp_path / "data" / "risk" / "manifest.json"
    m = json.loads(man.read_text())
    m["tables"] = [{"name": "frames.csv", "sha256": sha256_file(f)}]
    man.write_text(json.dumps(m))
    src = RiskSource(tmp_path / "data" / "risk", tmp_path / "data" / "disparity", None)
    geo = GeometricParams(subject_length=SUBJECT_LENGTH, subject_width=1.8)
    keys = ("fx", "fy", "cx", "cy", "baseline", "mount_x", "mount_height", "width", "height")
    cam = {k: float(src.camera[k]) for k in keys}
    rule = {
        name: GeometricRiskModel(GeometricParams(**{**geo.__dict__, "corridor_half_width": w}), cam)
        for name, w in (("ref", 1.0), ("ref_s1", 1.25), ("held", 1.0), ("held_s1", 1.25))
    }
    settings = SuiteSettings(
        acceptance=RISK,
        thresholds_s=(1.5, 1.0),
        primary_label="risk_thw_corridor",
        geometric=geo,
        main_variant="ref",
        variants={"ref_s1": {"replicate_of": "ref"}, "held_s1": {"replicate_of": "held"}},
        ci=CIConfig(100, 0, 0.95),
        holdout=Holdout(("roundabout",), group="held", reference="ref"),
    )
    metrics, pred = evaluate_suite(src, rule, settings)
    ho = metrics["holdout"]
    mask = (pred["template"] == "roundabout").to_numpy()
    assert ho["n_frames"] == int(mask.sum()) and ho["templates"] == ["roundabout"]
    y = pred["risk_thw_corridor"].to_numpy()
    ba = np.mean(
        [
            classification_metrics(y[mask], pred[f"pred_{v}"].to_numpy()[mask], 1.5)[
                "balanced_accuracy"
            ]
            for v in ("held", "held_s1")
        ]
    )
    assert ho["heldout"]["balanced_accuracy"] == pytest.approx(ba)
    std = metrics["groups"]["ref"]["at_1.5s"]["balanced_accuracy"]
    assert ho["drop"]["balanced_accuracy"]["estimate"] == pytest.approx(std - ba)
    t = metrics["targets"]["holdout_balanced_accuracy_drop"]
    assert t["value"] == pytest.approx(std - ba) and t["met"] == (std - ba <= 0.05)
    assert "comparisons" in metrics and all(
        0.0 <= v <= 1.0 for v in metrics["comparisons"]["secondary_holm"]["p_adjusted"].values()
    )


def test_shipped_verdict_uses_the_validation_cut() -> None:
    from traffictwin.api import LoadedRisk, decision_cut, risk_verdict

    class _M:
        meta = {"shipped": {"decision": {"1.5": {"cut": 0.02}}}}

    lr = LoadedRisk(_M(), "x")
    assert decision_cut(lr, 1.5) == 0.02 and decision_cut(lr, 1.0) is None
    v = risk_verdict(0.025, 10.0, 1.5, 0.02)  # THW 2 s > 1.5 s, but the risk is above the cut
    assert v["critical"] and v["decision_cut"] == 0.02 and v["thw_s"] == pytest.approx(2.0)
    assert not risk_verdict(0.025, 10.0, 1.5)["critical"]


def test_registry_check_accepts_rule_and_hybrid_configs() -> None:
    """The promotion gate's config check builds the rule / hybrid config, not a DAVE-2 one."""
    from traffictwin.risk.gate_eval import config_incompatibility

    cam = {**{k: float(v) for k, v in CAM.items()}, "width": 96.0, "height": 48.0}
    rule = GeometricRiskModel(GeometricParams(), cam)
    assert config_incompatibility({"config": rule.architecture()}) is None
    bad = {**rule.architecture(), "params": {"corridor_half_width": -1.0}}
    assert "not valid here" in config_incompatibility({"config": bad})
    hybrid_without_features = {"config": {"kind": "hybrid", "camera": cam}}
    assert "not valid here" in config_incompatibility(hybrid_without_features)


def test_select_on_validation_ships_the_rule_when_every_run_collapsed(tmp_path: Path) -> None:
    """select_risk's library part: validation figures of the networks on the primary label, both
    rules and the speed-only baseline; collapsed runs are no candidates, so the rule ships at its
    chosen half-width; the JSON layout is risk_selection.json's."""
    from test_risk_eval import _tiny_models
    from test_risk_training import write_synthetic_risk

    from traffictwin.risk.config import EvalRiskConfig, GeometricConfig, MetricParams
    from traffictwin.risk.selection_suite import (
        SelectionSetup,
        select_on_validation,
        shipped_rule,
    )

    write_synthetic_risk(tmp_path, n_shards=4, per_shard=8)
    src = RiskSource(tmp_path / "data" / "risk", tmp_path / "data" / "disparity", None)
    models = _tiny_models(tmp_path / "models")
    geo = GeometricConfig(
        half_widths=[1.0, 1.5], min_height=0.3, max_height=2.5, min_pixels=10, max_range=80.0
    )
    ev = EvalRiskConfig(
        thresholds_s=[1.5, 1.0],
        thw_cap_s=10.0,
        batch_size=8,
        main_variant="rgbd",
        geometric=geo,
        ci={},
        collapse_std=1.0,  # every network run counts as collapsed
    )
    subject = MetricParams(4.5, 1.8, "border", False, 0.0, 3.0)
    setup = SelectionSetup(ev, subject, "risk_thw_paper", {}, (), ())
    sel = select_on_validation(src, models, setup)
    val = src.split_frames("val")
    assert sel.n_frames == len(val) and sel.label == "risk_thw_paper"
    assert "rgbd_fov" not in sel.predictors  # another label
    assert {"rgbd", "gtdisp", "rgbd_speed", "geometric_sgm", "geometric_gt", "speed_only"} == set(
        sel.predictors
    )
    assert all(sel.predictors[v].collapsed for v in ("rgbd", "gtdisp", "rgbd_speed"))
    assert sel.learned == "rgbd" and sel.shipped.candidates == ["geometric_sgm"]
    assert sel.shipped.predictor == "geometric_sgm" and sel.shipped.kind == "geometric"
    rule = shipped_rule(sel, setup, src.camera)
    assert rule.params.corridor_half_width == sel.rules["geometric_sgm"].half_width
    js = sel.to_json()
    assert js["split"] == "val" and set(js["predictors"]["rgbd"]["decision"]) == {"1.5", "1"}
    assert set(js["rules"]["geometric_gt"]["candidates"]) == {"1", "1p5"}
    assert js["groups"]["rgbd"] == {
        "runs": ["rgbd"],
        "kind": "dave2",
        "roc_auc_mean": js["predictors"]["rgbd"]["roc_auc"],  # one run (None: one class)
    }
    json.dumps(js, allow_nan=False)  # strict JSON


def test_select_on_validation_without_positives_ships_the_rule_at_the_label_corridor(
    tmp_path: Path,
) -> None:
    """No critical validation frame (a THW threshold no frame reaches): nothing is chosen on
    validation, no NaN score decides; the rules take the label's corridor half-width, the SGM rule
    ships at it with the label's own cut, and the records and the model description say why."""
    from test_risk_eval import _tiny_models
    from test_risk_training import write_synthetic_risk

    from traffictwin.api import LoadedRisk
    from traffictwin.risk.config import EvalRiskConfig, GeometricConfig, MetricParams
    from traffictwin.risk.metric import risk_threshold
    from traffictwin.risk.selection_suite import (
        SelectionSetup,
        label_half_width,
        select_on_validation,
        shipped_rule,
    )

    write_synthetic_risk(tmp_path, n_shards=4, per_shard=8)
    src = RiskSource(tmp_path / "data" / "risk", tmp_path / "data" / "disparity", None)
    models = _tiny_models(tmp_path / "models")
    geo = GeometricConfig(
        half_widths=[0.5, 1.0], min_height=0.3, max_height=2.5, min_pixels=10, max_range=80.0
    )
    ev = EvalRiskConfig(
        thresholds_s=[0.01],  # no frame is this close: no positive on validation
        thw_cap_s=10.0,
        batch_size=8,
        main_variant="rgbd",
        geometric=geo,
        ci={},
        collapse_std=0.0,  # the networks compete
    )
    subject = MetricParams(4.5, 1.8, "border", False, 0.25, 3.0)
    setup = SelectionSetup(ev, subject, "risk_thw_paper", {}, (), ())
    sel = select_on_validation(src, models, setup)
    assert label_half_width(subject) == 2.0  # 3.5 m lane / 2 + 0.25 m margin
    for r in ("geometric_sgm", "geometric_gt"):
        assert sel.rules[r].half_width == 2.0
        assert sel.rules[r].note.startswith("not enough validation positives (n=0 critical of")
    sh = sel.shipped
    assert sh.predictor == "geometric_sgm" and sh.kind == "geometric"
    assert sh.note.startswith("not enough validation positives (n=0") and "2 m" in sh.note
    assert sh.decision["0.01"].cut == risk_threshold(0.01)
    assert shipped_rule(sel, setup, src.camera).params.corridor_half_width == 2.0
    js = sel.to_json()
    json.dumps(js, allow_nan=False)
    assert js["shipped"]["note"] == sh.note and js["rules"]["geometric_sgm"]["note"]

    class _Meta:
        meta = {"shipped": js["shipped"], "kind": "geometric"}

    described = LoadedRisk(_Meta(), "x").predictor
    assert "not enough validation positives" in described and "nan" not in described


def _learned_copy_of_gt(repo: Path) -> Path:
    """data/stereo_learned aligned 1:1 with data/risk whose ``disp_learned`` is the exact
    disparity (so the rule on it must equal the GT rule)."""
    from traffictwin.io.shards import Dataset, DatasetWriter

    risk = Dataset(repo / "data" / "risk", kind="risk")
    w = DatasetWriter(repo / "data" / "stereo_learned", "stereo_learned", {"synthetic": True}, 0)
    for i, sh in enumerate(risk.shards):
        gt = risk.load_shard(i)["disp_gt"]
        w.add_shard(
            int(sh["name"].split("-")[1].split(".")[0]), {"disp_learned": gt}, split=sh["split"]
        )
    w.finalize()
    return repo / "data" / "stereo_learned"


def test_rule_on_the_learned_disparity_is_tuned_and_evaluated_but_never_ships(
    tmp_path: Path,
) -> None:
    """With data/stereo_learned the corridor rule also runs on the learned stereo network's
    disparity: tuned on validation like the others, evaluated on test beside them with its paired
    difference to the SGM rule; it is no shipping candidate (the CLI computes SGM). Without the
    dataset it is absent, and asking the source for it names what is missing."""
    from traffictwin.risk.config import EvalRiskConfig, GeometricConfig, MetricParams
    from traffictwin.risk.selection_suite import SelectionSetup, select_on_validation

    write_sequences(tmp_path, n_shards=5, per_shard=18)
    learned = _learned_copy_of_gt(tmp_path)
    src = RiskSource(tmp_path / "data" / "risk", tmp_path / "data" / "disparity", None, learned)
    assert src.disparity_keys == {"disp_gt", "disp_sgm", "disp_learned"}
    geo = GeometricConfig(
        half_widths=[1.0, 2.0], min_height=0.3, max_height=2.5, min_pixels=10, max_range=80.0
    )
    ev = EvalRiskConfig(
        thresholds_s=[1.5, 1.0],
        thw_cap_s=10.0,
        batch_size=8,
        main_variant="x",
        geometric=geo,
        ci={},
        collapse_std=1e-3,
    )
    subject = MetricParams(SUBJECT_LENGTH, 1.8, "border", False, 0.0, 3.0)
    sel = select_on_validation(
        src, {}, SelectionSetup(ev, subject, "risk_thw_corridor", {}, (), ())
    )
    assert set(sel.rules) == {"geometric_sgm", "geometric_gt", "geometric_learned"}
    # the learned disparity is the exact one here: same validation table as the GT rule
    assert sel.rules["geometric_learned"].candidates == sel.rules["geometric_gt"].candidates
    assert "geometric_learned" not in sel.shipped.candidates

    settings = SuiteSettings(
        acceptance=RISK,
        thresholds_s=(1.5, 1.0),
        primary_label="risk_thw_corridor",
        geometric=GeometricParams(subject_length=SUBJECT_LENGTH, subject_width=1.8),
        ci=CIConfig(100, 0, 0.95),
    )
    rule = GeometricRiskModel(settings.geometric, src.camera, {"label": "risk_thw_corridor"})
    metrics, pred = evaluate_suite(src, {"shipped": rule}, settings)
    np.testing.assert_allclose(pred["pred_geometric_learned"], pred["pred_geometric_gt"])
    b = metrics["baselines"]
    assert b["geometric_learned"]["at_1.5s"] == b["geometric_gt"]["at_1.5s"]
    d = metrics["differences"]["geometric_learned|geometric_sgm"]
    assert d["kind"] == "disparity_source" and d["n_frames"] == len(src.split_frames("test"))

    plain = RiskSource(tmp_path / "data" / "risk", tmp_path / "data" / "disparity", None)
    _, pred_plain = evaluate_suite(plain, {"shipped": rule}, settings)
    assert "pred_geometric_learned" not in pred_plain
    with pytest.raises(ValueError, match="'disp_learned' requested but no stereo_learned"):
        next(plain.iter_arrays(plain.split_frames("test"), ["disp_learned"]))


def test_hybrid_on_the_learned_disparity_reads_it_everywhere_and_needs_its_network_to_serve(
    tmp_path: Path,
) -> None:
    """A hybrid with ``disparity: disp_learned`` takes its features from data/stereo_learned in
    training, validation and test alike, gets its paired difference to the SGM rule, and the API
    serves it only with the learned stereo network that computes that disparity (none given or
    packaged here: refused, saying how to give it)."""
    from traffictwin.api import ApiError
    from traffictwin.api.risk import load_risk
    from traffictwin.risk.predictors import HybridRiskModel, PredictorInputs, source_features

    with pytest.raises(ValueError, match="'disparity' must be one of"):
        HybridConfig(disparity="disp_gt")
    write_sequences(tmp_path, n_shards=5, per_shard=18)
    learned = _learned_copy_of_gt(tmp_path)
    src = RiskSource(tmp_path / "data" / "risk", tmp_path / "data" / "disparity", None, learned)
    geo = GeometricParams(subject_length=SUBJECT_LENGTH, subject_width=1.8)
    cfg = HybridConfig(half_widths=(1.0,), bin_edges=(-1.0, 1.0), epochs=2, hidden=4)
    cfg_l = HybridConfig.from_dict({**cfg.to_dict(), "disparity": "disp_learned"})
    train = src.split_frames("train")
    x_sgm, _ = source_features(src, train, src.camera, geo, cfg)
    x_l, rows = source_features(src, train, src.camera, geo, cfg_l)
    x_gt = corridor_features_of(src, rows, "disp_gt", geo, cfg)
    np.testing.assert_array_equal(x_l, x_gt)  # the learned source here is the exact disparity
    assert not np.array_equal(x_l, x_sgm)

    net, _ = fit_hybrid(x_l, np.full(len(x_l), 3.0), cfg_l, 0)
    model = HybridRiskModel(
        net,
        cfg_l,
        geo,
        src.camera,
        {"label": "risk_thw_corridor"},
        PredictorInputs(("disp_learned",)),
    )
    settings = SuiteSettings(
        acceptance=RISK,
        thresholds_s=(1.5, 1.0),
        primary_label="risk_thw_corridor",
        geometric=geo,
        ci=CIConfig(50, 0, 0.95),
    )
    rule = GeometricRiskModel(geo, src.camera, {"label": "risk_thw_corridor"})
    metrics, pred = evaluate_suite(src, {"shipped": rule, "hybrid_learned": model}, settings)
    test = src.split_frames("test")
    want = model.predict_features(corridor_features_of(src, test, "disp_learned", geo, cfg_l))
    np.testing.assert_allclose(np.sort(pred["pred_hybrid_learned"]), np.sort(want), rtol=1e-6)
    assert metrics["differences"]["hybrid_learned|geometric_sgm"]["kind"] == "disparity_source"

    save_predictor(model, tmp_path / "models" / "hybrid_learned", {"label": "risk_thw_corridor"})
    back = load_risk_model(tmp_path / "models" / "hybrid_learned")
    assert back.config.disparity == "disp_learned" and back.cfg.inputs == ("disp_learned",)
    with pytest.raises(ApiError, match="learned stereo network's disparity.*--stereo-model"):
        load_risk(tmp_path / "models" / "hybrid_learned")


def corridor_features_of(src, frames, key: str, geo, cfg) -> np.ndarray:
    """The hybrid features of ``frames`` computed from the source's array ``key`` directly."""
    from traffictwin.risk.predictors import corridor_features

    return np.concatenate(
        [
            corridor_features(arr[key], rows["speed"].to_numpy(np.float64), src.camera, geo, cfg)
            for rows, arr in src.iter_arrays(frames, [key])
        ]
    )


def test_the_shipped_model_is_logged_with_its_served_signature_and_a_validation_example(
    tmp_path: Path, mlflow_uri: str, monkeypatch
) -> None:
    """Every registered model carries a signature and an input example: the shipped rule's is
    what its pyfunc serves (speed, then its disparity), filled from a validation frame, and the
    served model answers the example with the rule's own risk."""
    import mlflow

    from pipelines import select_risk
    from traffictwin.mlops import serving
    from traffictwin.risk.predictors import PackedPredictor
    from traffictwin.risk.training import RiskSource

    monkeypatch.chdir(tmp_path)
    write_sequences(tmp_path, n_shards=4, per_shard=6)
    src = RiskSource(tmp_path / "data" / "risk", tmp_path / "data" / "disparity", None)
    cam = {k: float(v) for k, v in src.camera.items() if k in CAM or k in ("width", "height")}
    rule = GeometricRiskModel(GeometricParams(corridor_half_width=1.0), cam)
    folder = save_predictor(rule, tmp_path / "shipped", {"label": "risk_thw_corridor"})
    signature, x = select_risk.serving_signature(folder, src)
    first = src.split_frames("val").iloc[:1]
    _, arr = next(iter(src.iter_arrays(first, ["disp_sgm"])))
    assert x.shape == (1, 1 + 48 * 96) and x[0, 0] == pytest.approx(first["speed"].iloc[0])
    np.testing.assert_array_equal(x[0, 1:], arr["disp_sgm"][0].ravel())
    assert tuple(signature.inputs.to_dict()[0]["tensor-spec"]["shape"]) == (-1, 1 + 48 * 96)
    served = serving.TrafficTwinModel(PackedPredictor(load_risk_model(folder)), "risk")
    want = rule.predict(disp_sgm=arr["disp_sgm"], speed=first["speed"].to_numpy())
    np.testing.assert_allclose(served.predict(x), want)

    sel = {
        "shipped": {"predictor": "geometric_sgm", "kind": "geometric"},
        "predictors": {},
        "rules": {"geometric_sgm": {"half_width": 1.0}},
        "criterion": "ROC-AUC",
    }
    rec = select_risk.track_shipped({"profile": {"name": "test"}}, sel, folder, src)
    info = mlflow.models.get_model_info(rec["model_uri"])
    assert info.signature is not None and info.saved_input_example_info is not None


def test_hybrid_on_the_learned_disparity_competes_for_shipping() -> None:
    """Its runs are shipping candidates beside the learned group and the SGM rule (and win with
    the highest validation AUC); the group that competes as 'learned' stays the main / hybrid one,
    and a collapsed run never ships."""
    from traffictwin.risk.selection_suite import (
        LEARNED_DISPARITY_GROUP,
        GroupChoice,
        PredictorChoice,
        RuleChoice,
        _ship,
    )

    def pc(kind: str, group: str, auc: float, collapsed: bool = False) -> PredictorChoice:
        return PredictorChoice(kind, group, 0.05, collapsed, auc, 100, {})

    predictors = {
        "geometric_sgm": pc("geometric", "geometric_sgm", 0.90),
        "hybrid": pc("hybrid", "hybrid", 0.93),
        "hybrid_s1": pc("hybrid", "hybrid", 0.92),
        "hybrid_learned": pc("hybrid", LEARNED_DISPARITY_GROUP, 0.95),
        "hybrid_learned_s1": pc("hybrid", LEARNED_DISPARITY_GROUP, 0.97, collapsed=True),
    }
    groups = {
        "hybrid": GroupChoice(["hybrid", "hybrid_s1"], "hybrid", 0.925),
        LEARNED_DISPARITY_GROUP: GroupChoice(
            ["hybrid_learned", "hybrid_learned_s1"], "hybrid", 0.96
        ),
    }
    rule = RuleChoice(1.0, [])
    best, shipped = _ship(predictors, groups, "headline", rule, None)
    assert best == "hybrid"  # the group compared with the rule in the findings is unchanged
    assert shipped.predictor == "hybrid_learned"
    assert shipped.candidates == ["geometric_sgm", "hybrid", "hybrid_learned", "hybrid_s1"]
    # without the learned-disparity runs the SGM hybrid ships, as before
    del groups[LEARNED_DISPARITY_GROUP]
    assert _ship(predictors, groups, "headline", rule, None)[1].predictor == "hybrid"


def test_a_shipped_learned_disparity_hybrid_carries_its_stereo_network(tmp_path, monkeypatch):
    import types

    import pipelines.select_risk as sr
    from traffictwin.api.risk import PACKAGED_STEREO

    def folder(name: str, sha: str) -> Path:
        d = tmp_path / name
        d.mkdir(parents=True)
        (d / "model.ckpt").write_bytes(name.encode())
        (d / "model_meta.json").write_text(json.dumps({"ckpt_sha256": sha, "what": name}))
        return d

    stereo = folder("stereo_learned", "s")
    folder("hybrids/hybrid_learned", "h")
    folder("hybrids/hybrid", "g")
    shipped = tmp_path / "risk_shipped"
    monkeypatch.setattr(sr, "STEREO_MODEL", stereo)
    monkeypatch.setattr(sr, "SHIPPED_RISK_MODEL", shipped)
    monkeypatch.setattr(sr, "hybrid_model_dir", lambda n: tmp_path / "hybrids" / n)

    def publish(name: str) -> None:
        sel = types.SimpleNamespace(shipped=types.SimpleNamespace(predictor=name))
        monkeypatch.setattr(sr, "asdict", lambda s: {"predictor": s.predictor})
        setup = types.SimpleNamespace(primary="risk")
        sr._publish_shipped(sel, setup, {}, None, [1, 2], learned=["hybrid_learned"])

    publish("hybrid_learned")
    assert (shipped / "model.ckpt").read_bytes() == b"hybrids/hybrid_learned"
    assert (shipped / PACKAGED_STEREO / "model.ckpt").read_bytes() == b"stereo_learned"
    assert json.loads((shipped / "model_meta.json").read_text())["shipped"] == {
        "predictor": "hybrid_learned"
    }
    # the next selection ships the SGM hybrid: no stereo network is left behind
    publish("hybrid")
    assert (shipped / "model.ckpt").read_bytes() == b"hybrids/hybrid"
    assert not (shipped / PACKAGED_STEREO).exists()
