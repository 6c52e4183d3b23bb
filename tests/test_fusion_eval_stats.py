"""Fusion evaluation statistics: per-pair u histograms, cluster-bootstrap intervals (Dice, AUROC),
paired differences, targets, networks per row, bad input (fast, synthetic)."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from _acceptance import thresholds

from traffictwin.acceptance import Threshold
from traffictwin.fusion import evaluation as ev
from traffictwin.fusion.evaluation.intervals import lohi, scenario_draws
from traffictwin.fusion.evaluation.targets import judge
from traffictwin.fusion.metrics import UncertaintyAUROC, auroc_from_hist, u_error_histograms
from traffictwin.grid import GridSpec
from traffictwin.io.jsonio import json_clean
from traffictwin.io.shards import DatasetError, DatasetWriter

CI = ev.CIConfig(n_boot=400, seed=0, level=0.95)
FUSION = thresholds("fusion")  # acceptance.fusion
ROOT = Path(__file__).resolve().parents[1]


def masses(cells: list[tuple[float, float]]) -> np.ndarray:
    """(1, 2, 1, n) masses from (m_F, m_O) per cell."""
    a = np.array(cells, dtype=np.float64).T  # (2, n)
    return a[None, :, None, :]


def frame(pid, **cols) -> pd.DataFrame:
    return pd.DataFrame({"pair_id": np.asarray(pid, dtype=np.int64), **cols})


# -- metrics ---------------------------------------------------------------------------------------
def test_u_error_histograms_by_hand():
    # labels: occ, occ, free, unknown; predictions: right (u=0.15), wrong (u=0.9), right (u=0.55)
    lab = masses([(0.0, 1.0), (0.0, 1.0), (1.0, 0.0), (0.0, 0.0)])
    pred = masses([(0.0, 0.85), (0.1, 0.0), (0.45, 0.0), (0.5, 0.5)])
    pos, neg = u_error_histograms(lab, pred, bins=10)
    assert pos.shape == neg.shape == (1, 10)
    np.testing.assert_array_equal(pos[0], np.eye(10, dtype=int)[9])  # the one wrong cell, u = 0.9
    np.testing.assert_array_equal(neg[0], np.eye(10, dtype=int)[1] + np.eye(10, dtype=int)[5])
    two = np.concatenate([lab, lab]), np.concatenate([pred, masses([(0, 1)] * 4)])
    p2, n2 = u_error_histograms(*two, bins=10)
    assert p2.shape == (2, 10) and p2[1].sum() == 1 and n2[1].sum() == 2  # per sample


def test_auroc_from_hist_on_a_batch_of_histograms():
    pos = np.array([[0, 0, 1], [1, 0, 0], [0, 1, 1], [0, 0, 0]])
    neg = np.array([[1, 0, 0], [0, 0, 1], [0, 1, 1], [1, 1, 0]])
    got = auroc_from_hist(pos, neg)
    assert isinstance(got, np.ndarray) and got.shape == (4,)
    np.testing.assert_allclose(got[:3], [1.0, 0.0, auroc_from_hist(pos[2], neg[2])])
    assert math.isnan(got[3])  # no positive
    with pytest.raises(ValueError, match="differ"):
        auroc_from_hist(np.ones(3), np.ones(4))


def test_uncertainty_auroc_keeps_the_per_sample_histograms():
    rng = np.random.default_rng(0)
    lab = rng.dirichlet([1, 1, 1], size=(3, 4, 5))[..., :2].transpose(0, 3, 1, 2)
    pred = rng.dirichlet([1, 1, 1], size=(3, 4, 5))[..., :2].transpose(0, 3, 1, 2)
    a = UncertaintyAUROC(bins=16, keep_samples=True)
    a.update(lab[:2], pred[:2])
    a.update(lab[2:], pred[2:])
    pos, neg = a.sample_histograms()
    assert pos.shape == (3, 16)
    np.testing.assert_array_equal(pos.sum(0), a.pos)
    np.testing.assert_array_equal(neg.sum(0), a.neg)
    with pytest.raises(ValueError, match="keep_samples"):
        UncertaintyAUROC(bins=16).sample_histograms()


# -- intervals -------------------------------------------------------------------------------------
def _two_scenarios() -> tuple[pd.DataFrame, np.ndarray, np.ndarray]:
    """Scenario 1: one pair, TP=1 (Dice 1), u perfectly flags errors (AUROC 1); scenario 2: one
    pair, FP=FN=1 (Dice 0), AUROC 0. Pooled: Dice 2/4 = 0.5, AUROC 0.5."""
    f = frame(
        [1000, 2000],
        kld_fou=[0.2, 0.4],
        kld_fo=[0.1, 0.3],
        u_mean=[0.5, 0.7],
        tp_occ=[1, 0],
        fp_occ=[0, 1],
        fn_occ=[0, 1],
        tp_free=[1, 1],
        fp_free=[0, 0],
        fn_free=[0, 0],
    )
    pos = np.array([[0, 1], [1, 0]])
    neg = np.array([[1, 0], [0, 1]])
    return f, pos, neg


def test_row_intervals_resample_scenarios_by_hand():
    f, pos, neg = _two_scenarios()
    iv = ev.row_intervals(f, pos, neg, CI)
    assert set(iv) == set(ev.CI_KEYS)
    # resamples {1,1}, {2,2}, {1,2}: Dice 1, 0, 0.5; AUROC 1, 0, 0.5; KLD(b) 0.2, 0.4, 0.3
    assert iv["dice_occ"].estimate == pytest.approx(0.5)
    assert (iv["dice_occ"].lo, iv["dice_occ"].hi) == (0.0, 1.0)
    assert iv["u_auroc"].estimate == pytest.approx(0.5)
    assert (iv["u_auroc"].lo, iv["u_auroc"].hi) == (0.0, 1.0)
    assert iv["kld_fou_mean"].estimate == pytest.approx(0.3)
    assert (iv["kld_fou_mean"].lo, iv["kld_fou_mean"].hi) == pytest.approx((0.2, 0.4))
    assert iv["dice_free"].estimate == 1.0 and iv["dice_free"].lo == iv["dice_free"].hi == 1.0
    assert iv["dice_occ"].n_groups == 2
    assert ev.row_intervals(f, pos, neg, CI) == iv  # deterministic for a seed


def test_row_intervals_dice_boot_matches_a_direct_resample():
    rng = np.random.default_rng(3)
    n = 30
    pid = 1000 * rng.integers(1, 8, n) + np.arange(n)
    cnt = {f"{k}_{c}": rng.integers(0, 20, n) for k in ("tp", "fp", "fn") for c in ("occ", "free")}
    f = frame(pid, kld_fou=rng.random(n), kld_fo=rng.random(n), u_mean=rng.random(n), **cnt)
    pos, neg = rng.integers(0, 5, (n, 8)), rng.integers(0, 5, (n, 8))
    iv = ev.row_intervals(f, pos, neg, CI)
    # the same draws, one resample at a time
    scen = pid // 1000
    groups = np.unique(scen)
    draws = scenario_draws(len(groups), CI)
    codes = np.searchsorted(groups, scen)
    w = draws[:, codes]  # (n_boot, n) weight of each pair in each resample
    tp, fp, fn = (w @ cnt[f"{k}_occ"] for k in ("tp", "fp", "fn"))
    lo, hi = np.quantile(2 * tp / (2 * tp + fp + fn), [0.025, 0.975])
    assert (iv["dice_occ"].lo, iv["dice_occ"].hi) == pytest.approx((lo, hi))
    au = [auroc_from_hist(wi @ pos, wi @ neg) for wi in w]
    assert (iv["u_auroc"].lo, iv["u_auroc"].hi) == pytest.approx(
        tuple(np.quantile(au, [0.025, 0.975]))
    )


def test_paired_intervals_align_pairs_and_share_resamples():
    f, _, _ = _two_scenarios()
    g = f.assign(kld_fou=f.kld_fou - 0.1, kld_fo=f.kld_fo + 0.05)
    d, n = ev.paired_intervals(f, g, CI)
    assert n == 2 and set(d) == set(ev.DIFF_KEYS)
    # a constant shift: every resample has the same difference
    assert (
        d["kld_fou_mean"].estimate,
        d["kld_fou_mean"].lo,
        d["kld_fou_mean"].hi,
    ) == pytest.approx((0.1, 0.1, 0.1))
    assert d["kld_fo_mean"].hi == pytest.approx(-0.05)
    assert (d["dice_occ"].estimate, d["dice_occ"].lo, d["dice_occ"].hi) == (0.0, 0.0, 0.0)
    # b evaluated on one pair only (a slow method's subset): the difference is over that pair
    d1, n1 = ev.paired_intervals(f, g.iloc[[1]], CI)
    assert n1 == 1 and d1["kld_fou_mean"].estimate == pytest.approx(0.1)
    assert ev.paired_intervals(f, g.assign(pair_id=[5000, 6000]), CI) == ({}, 0)


# -- targets ---------------------------------------------------------------------------------------
def test_judge_pass_fail_and_whether_the_ci_is_beyond_the_threshold():
    from traffictwin.stats import Interval

    le, ge = Threshold("<=", 0.3), Threshold(">=", 0.85)
    assert judge(Interval(0.2, 0.1, 0.25), le).status == "pass"
    assert judge(Interval(0.2, 0.1, 0.25), le).ci_beyond_threshold
    assert not judge(Interval(0.2, 0.1, 0.35), le).ci_beyond_threshold
    r = judge(Interval(0.8, 0.7, 0.9), ge)
    assert r.status == "fail" and not r.ci_beyond_threshold
    assert judge(Interval(0.8, 0.7, 0.84), ge).ci_beyond_threshold
    assert judge(Interval(math.nan, 0, 1), le).status == "not evaluated"


def _row(pid, kld_fou, tp_occ=10, fp_occ=0, fn_occ=0, u=0.5, label_u=0.5):
    n = len(pid)
    return frame(
        pid,
        kld_fou=np.broadcast_to(kld_fou, n).astype(float),
        kld_fo=np.zeros(n),
        u_mean=np.full(n, u),
        label_u_mean=np.full(n, label_u),
        tp_occ=np.full(n, tp_occ),
        fp_occ=np.full(n, fp_occ),
        fn_occ=np.full(n, fn_occ),
        tp_free=np.full(n, 5),
        fp_free=np.zeros(n, int),
        fn_free=np.zeros(n, int),
    )


def _hand_rows() -> tuple[np.ndarray, dict]:
    """Five pairs of three scenarios at A, C, D: naive, dnn (better; a false occupied cell at D)
    and the ego's own map, per (configuration, method)."""
    pid = np.array([1000, 1001, 2000, 2001, 3000])
    own = {}
    for c in ("A", "C", "D"):
        own[(c, "naive")] = _row(pid, [1.0, 2.0, 1.0, 2.0, 1.0])
        own[(c, "dnn")] = _row(pid, [0.2, 0.4, 0.2, 0.4, 0.2], fp_occ=1 if c == "D" else 0, u=0.55)
        own[(c, "ego")] = _row(pid, 1.0, fp_occ=2)
    return pid, own


def test_targets_by_hand_and_not_evaluated_when_absent():
    pid, own = _hand_rows()
    metrics = {"test": {c: {} for c in ("A", "C", "D")}, "diff": {}}
    for (c, row), f in own.items():
        iv = ev.row_intervals(f, np.zeros((5, 4)), np.zeros((5, 4)), CI)
        metrics["test"][c][row] = {k: iv[k].estimate for k in ev.CI_KEYS} | {
            f"{k}_ci": lohi(iv[k]) for k in ev.CI_KEYS
        }
    t = ev.fusion_targets(own, metrics, CI, 0.5, 1.0, FUSION)
    assert set(t) == set(ev.JUDGES)
    # (a) every pair's ratio is 0.2: the ratio of means is 0.2 in every resample
    a = t["kld_ratio_vs_naive"]["per_config"]["C"]
    assert (a["value"], a["lo"], a["hi"], a["status"]) == pytest.approx((0.2, 0.2, 0.2, "pass"))
    # (b) Dice occ at A is 1; (c) at D 2*10/(2*10+1) = 20/21: drop 1/21 < 10 %
    assert t["dice_occ_at_A"]["status"] == "pass"
    assert t["dice_occ_drop_A_to_D"]["per_config"]["D"]["value"] == pytest.approx(1 / 21)
    # (d) ego has FP=2 per pair: Dice 20/22; the network's is higher at A and C
    assert t["dice_occ_vs_ego"]["per_config"]["A"]["value"] == pytest.approx(1 - 20 / 22)
    # (e) no wrong cell histogram: AUROC undefined -> not evaluated, never pass
    assert t["u_auroc"]["status"] == "not evaluated"
    # (f) |0.55 - 0.5| = 0.05 <= 0.1
    f = t["u_mean_vs_label"]["per_config"]["D"]
    assert f["value"] == pytest.approx(0.05) and f["status"] == "pass"
    # (g) no registered+network row
    assert t["hybrid_vs_registered"]["status"] == "not evaluated"
    assert t["hybrid_vs_registered"]["per_config"]["C"]["status"] == "not evaluated"
    # a network that never predicts occupied at A: no relative drop (not a crash, not a pass)
    zero = dict(own)
    zero[("A", "dnn")] = _row(pid, 0.2, tp_occ=0, fn_occ=3)
    t0 = ev.fusion_targets(zero, metrics, CI, 0.5, 1.0, FUSION)["dice_occ_drop_A_to_D"][
        "per_config"
    ]["D"]
    assert t0["status"] == "not evaluated" and "Dice occ at A is 0.0" in t0["why"]
    # a target at a configuration that was not evaluated (B absent) is not a pass
    del own[("A", "dnn")]
    metrics["test"].pop("A")
    t2 = ev.fusion_targets(own, metrics, CI, 0.5, 1.0, FUSION)
    assert t2["dice_occ_at_A"]["status"] == "not evaluated"
    assert t2["dice_occ_drop_A_to_D"]["status"] == "not evaluated"


def _target_inputs() -> tuple[dict, dict]:
    """Per-pair frames and metrics where every target has a value (see the hand cases above)."""
    pid, own = _hand_rows()
    own[("D", ev.LEARNED)] = frame(pid, ms=np.full(5, 10.0), reg_success=np.ones(5))
    own[("D", ev.LEARNED_REFINED)] = frame(pid, ms=np.full(5, 30.0), reg_success=np.ones(5))
    metrics = {"test": {c: {} for c in ("A", "C", "D")}, "diff": {}}
    for (c, row), f in own.items():
        if row in (ev.LEARNED, ev.LEARNED_REFINED):
            metrics["test"][c][row] = {}
            continue
        iv = ev.row_intervals(f, np.zeros((5, 4)), np.zeros((5, 4)), CI)
        metrics["test"][c][row] = {k: iv[k].estimate for k in ev.CI_KEYS} | {
            f"{k}_ci": lohi(iv[k]) for k in ev.CI_KEYS
        }
    vs_reg = {
        ev.HEADLINE: {"estimate": -0.1, "lo": -0.2, "hi": -0.05},
        "dice_occ": {"estimate": 0.0, "lo": -0.01, "hi": 0.01},
    }
    for c in ("C", "D"):
        metrics["diff"][c] = {
            ev.NETWORK: {
                "vs_registered": vs_reg,
                f"vs_{ev.PER_CONFIG_NETWORK}": {
                    ev.HEADLINE: {"estimate": 0.001, "lo": -0.001, "hi": 0.003}
                },
            },
            ev.HYBRID: {"vs_registered": vs_reg},
            ev.LEARNED_NETWORK: {"vs_registered": vs_reg},
        }
    metrics["diff"]["D"][ev.LEARNED] = {
        "vs_registered": {
            "success_rate": {"estimate": 0.2, "lo": 0.1, "hi": 0.3, "n_pairs": 5},
        }
    }
    metrics["diff"]["D"][ev.LEARNED_REFINED] = {
        "vs_registered": {
            "success_rate": {"estimate": 0.15, "lo": 0.07, "hi": 0.25, "n_pairs": 5},
        }
    }
    # the network at A and learned + network at D, read as fusion.json has them
    metrics["test"]["A"][ev.NETWORK] |= {
        ev.HEADLINE: 0.001,
        f"{ev.HEADLINE}_ci": {"lo": 0.0008, "hi": 0.0012},
    }
    metrics["test"]["D"][ev.LEARNED_NETWORK] = {
        ev.HEADLINE: 0.008,
        f"{ev.HEADLINE}_ci": {"lo": 0.007, "hi": 0.011},
    }
    return own, metrics


# target -> (configuration judged, a threshold that turns its pass into a fail)
FLIPS = {
    "kld_ratio_vs_naive": ("C", 0.1),  # ratio 0.2
    "network_vs_registered": ("C", -0.1),  # upper end -0.05
    "hybrid_vs_registered": ("D", -0.1),
    "learned_kld_vs_registered": ("D", -0.1),
    "one_vs_per_config": ("D", 0.001),  # upper end 0.003
    "kld_at_A": ("A", 0.0005),  # KLD(b) 0.001
    "dice_occ_at_A": ("A", 1.01),  # Dice 1
    "learned_network_kld_at_D": ("D", 0.005),  # KLD(b) 0.008
    "dice_occ_drop_A_to_D": ("D", 0.01),  # drop 1/21
    "dice_occ_vs_ego": ("A", 0.5),  # 1 - 20/22
    "u_mean_vs_label": ("D", 0.01),  # |0.55 - 0.5|
    "learned_success_vs_registered": ("D", 0.25),  # gain 0.2
    "learned_success_gain_at_D": ("D", 0.25),
    "learned_success_at_D": ("D", 1.01),  # rate 1
    "learned_runtime_ms": ("D", 5.0),  # 10 ms
    "refined_success_gain_at_D": ("D", 0.2),  # gain 0.15
    "refined_success_at_D": ("D", 1.01),  # rate 1
}


def test_every_verdict_reads_its_threshold_from_the_config():
    """Each target follows its acceptance threshold: moving one value flips its verdict."""
    own, metrics = _target_inputs()
    base = ev.fusion_targets(own, metrics, CI, 0.5, 1.0, FUSION)
    # u_auroc has no value here (no wrong-cell histograms); every other target is flipped below
    # (training_converged: judged on the training record, its own test below)
    assert set(FLIPS) == set(ev.JUDGES) - {"u_auroc", "training_converged"}
    for name, (c, threshold) in FLIPS.items():
        assert base[name]["per_config"][c]["status"] == "pass", name
        moved = {**FUSION, name: dataclasses.replace(FUSION[name], value=threshold)}
        t = ev.fusion_targets(own, metrics, CI, 0.5, 1.0, moved)[name]
        assert t["threshold"] == threshold and t["per_config"][c]["status"] == "fail", name
    # u_auroc: the config's threshold decides a value read from metrics
    metrics["test"]["D"]["dnn"] |= {"u_auroc": 0.9, "u_auroc_ci": {"lo": 0.8, "hi": 0.95}}
    t = ev.fusion_targets(own, metrics, CI, 0.5, 1.0, FUSION)
    assert t["u_auroc"]["per_config"]["D"]["status"] == "pass"
    moved = {**FUSION, "u_auroc": dataclasses.replace(FUSION["u_auroc"], value=0.95)}
    t = ev.fusion_targets(own, metrics, CI, 0.5, 1.0, moved)
    assert t["u_auroc"]["per_config"]["D"]["status"] == "fail"
    # a missing threshold is named
    with pytest.raises(ValueError, match="no acceptance threshold for .'u_auroc'"):
        less = {k: v for k, v in FUSION.items() if k != "u_auroc"}
        ev.fusion_targets(own, metrics, CI, 0.5, 1.0, less)


@pytest.mark.parametrize(
    ("training", "status", "value"),
    [
        ({"best_epoch": 31, "epochs": 44, "stopped_early": True}, "pass", 32 / 44),
        ({"best_epoch": 35, "epochs": 45, "stopped_early": True}, "pass", 0.8),  # on the line
        ({"best_epoch": 40, "epochs": 44, "stopped_early": True}, "fail", 41 / 44),
        ({"best_epoch": 10, "epochs": 35, "stopped_early": False}, "fail", 11 / 35),  # the cap
        ({"best_epoch": 44, "epochs": 44, "stopped_early": True}, "not evaluated", None),
        (None, "not evaluated", None),
    ],
)
def test_training_converged_is_judged_on_the_best_epoch_s_place_and_early_stopping(
    training, status, value
):
    """(best_epoch + 1) / epochs <= 0.8, and early stopping ended the run; a run the epoch cap
    ended fails whatever its best epoch (it may still have been improving)."""
    own, metrics = _target_inputs()
    t = ev.fusion_targets(own, metrics, CI, 0.5, 1.0, FUSION, training)["training_converged"]
    v = t["per_config"]["mixed"]
    assert (t["threshold"], t["op"]) == (0.8, "<=")
    assert v["status"] == status and t["status"] == status
    assert v["value"] == pytest.approx(value) if value is not None else v["value"] is None
    if training and not training["stopped_early"]:
        assert "epoch cap (35)" in v["why"]
    if status != "not evaluated":
        assert (v["best_epoch"], v["epochs"]) == (training["best_epoch"], training["epochs"])
    # the threshold comes from the config
    moved = {
        **FUSION,
        "training_converged": dataclasses.replace(FUSION["training_converged"], value=0.7),
    }
    ok = {"best_epoch": 31, "epochs": 44, "stopped_early": True}
    t = ev.fusion_targets(own, metrics, CI, 0.5, 1.0, moved, ok)["training_converged"]
    assert t["per_config"]["mixed"]["status"] == "fail"


# -- evaluate with networks per row ------------------------------------------------------------------
def _random_masses(rng, n, h, w):
    d = rng.dirichlet([1.0, 1.0, 1.0], size=(n, h, w))
    return np.moveaxis(d[..., :2], -1, 1).astype(np.float32)


def _tiny_net(seed: int):
    import torch

    from traffictwin.fusion.deeplab import DeepLabSpec, DeepLabV3Plus
    from traffictwin.fusion.resnet import ResNetSpec

    torch.manual_seed(seed)
    spec = DeepLabSpec(
        backbone=ResNetSpec(block="basic", layers=(1, 1, 1, 1), base_width=8),
        aspp_channels=16,
        low_level_channels=8,
        decoder_channels=16,
    )
    return DeepLabV3Plus(spec).eval()


def _eval_config():
    from omegaconf import OmegaConf

    from traffictwin.fusion.config import fusion_eval_config

    cfg = OmegaConf.create(yaml.safe_load((ROOT / "params.yaml").read_text()))
    fc = fusion_eval_config(cfg)
    return dataclasses.replace(
        fc, max_pairs=None, registered_max_pairs=None, cross_max_pairs=3, batch_size=4
    )


def _synthetic(configs=("A", "C", "D"), n=6, hw=32):
    from traffictwin.evidential.dempster import dempster

    rng = np.random.default_rng(0)
    pid = np.array([1000, 1001, 2000, 2001, 3000, 3001][:n])
    m1, m2 = _random_masses(rng, n, hw, hw), _random_masses(rng, n, hw, hw)
    label = np.asarray(dempster(m1, m2), np.float32)
    z = np.zeros((n, 3))
    data = {
        c: {
            "inputs": np.concatenate([m1, m2], axis=1),
            "label": label,
            "noise": z,
            "rel_pose_true": z,
            "rel_pose_noisy": z,
            "pair_id": pid,
        }
        for c in configs
    }
    raw = {"map1": m1, "map2": m2, "label": label, "pose1": z, "pose2": z, "pair_id": pid}
    return data, raw, GridSpec(hw, hw, 0.5)


@pytest.mark.usefixtures("single_torch_thread")
def test_evaluate_runs_each_row_where_it_has_a_network():
    data, raw, grid = _synthetic()
    one = _tiny_net(0)
    networks = {
        "dnn": dict.fromkeys(data, one),  # the one network at every configuration
        "dnn[paper]": {"D": _tiny_net(7)},
        "registered+network": {"C": _tiny_net(8), "D": _tiny_net(9)},
        "dnn[per-config]": {c: _tiny_net(i + 1) for i, c in enumerate(data)},
    }
    res = ev.evaluate(data, raw, networks, grid, _eval_config(), CI, FUSION)
    m = res.metrics
    assert "dnn[paper]" in m["test"]["D"] and "dnn[paper]" not in m["test"]["C"]
    assert "registered+network" in m["test"]["C"] and "registered+network" not in m["test"]["A"]
    # the cross table is the per-configuration networks' only (the one network is everywhere)
    names = ["dnn[per-config]-A", "dnn[per-config]-C", "dnn[per-config]-D"]
    assert sorted(m["cross"]) == names
    assert all(sorted(v) == ["A", "C", "D"] for v in m["cross"].values())
    s = res.samples
    assert set(s.method) >= {"dnn[paper]", "registered+network", "dnn[per-config]-A"}
    # the one network is compared with each configuration's own network, pair by pair
    for c in data:
        d = m["diff"][c]["dnn"]["vs_dnn[per-config]"]["kld_fou_mean"]
        assert d["lo"] <= d["estimate"] <= d["hi"] and d["n_pairs"] == 6
    t = m["targets"]["one_vs_per_config"]
    assert set(t["per_config"]) == {"A", "C", "D"}
    assert t["status"] in ("pass", "fail")
    # every row of a configuration on the same pairs (registered_max_pairs null)
    for c in data:
        main = s[(s.config == c) & ~s.method.str.startswith("dnn[per-config]-")]
        assert main.groupby("method").pair_id.apply(sorted).map(tuple).nunique() == 1
    # intervals around every estimate, differences against naive and registered
    for c, rows in m["test"].items():
        for row, v in rows.items():
            for k in ev.CI_KEYS:
                lo, hi = v[f"{k}_ci"]["lo"], v[f"{k}_ci"]["hi"]
                if math.isfinite(v[k]):
                    assert lo - 1e-12 <= v[k] <= hi + 1e-12, (c, row, k)
    d = m["diff"]["D"]["dnn[paper]"]
    assert set(d) == {"vs_naive", "vs_registered"} and set(d["vs_naive"]) == set(ev.DIFF_KEYS)
    assert d["vs_naive"]["kld_fou_mean"]["estimate"] == pytest.approx(
        m["test"]["D"]["dnn[paper]"]["kld_fou_mean"] - m["test"]["D"]["naive"]["kld_fou_mean"]
    )
    assert "vs_naive" not in m["diff"]["D"]["naive"]
    assert "vs_registered" not in m["diff"]["D"]["registered"]
    lu = m["label"]["A"]["u_mean"]
    assert lu == pytest.approx(
        float(s[(s.config == "A") & (s.method == "naive")].label_u_mean.mean())
    )
    # wall times (and the target judged on them) only in res.timings: never in fusion.json / samples
    assert set(m["targets"]) == set(ev.JUDGES) - set(ev.TIMING_TARGETS)
    assert set(res.timings["targets"]) == set(ev.TIMING_TARGETS)
    assert "ms" not in s and "runtime_ms_per_pair" not in m
    assert "ms_per_pair" not in m["test"]["D"]["dnn[paper]"]
    assert (
        res.timings["ms_per_pair"]["D"]["dnn[paper]"] > 0
        and "dnn[per-config]-A" not in res.timings["ms_per_pair"]["D"]
    )
    assert set(res.timings["runtime_ms_per_pair"]) == set(
        s.method[~s.method.str.startswith("dnn[per-config]-")]
    )
    assert m["targets"]["hybrid_vs_registered"]["per_config"]["D"]["status"] in ("pass", "fail")
    assert m["bootstrap"]["n_boot"] == CI.n_boot
    # MLflow numbers of the variant's own run: its row is `test/`, names MLflow-safe
    flat = ev.mlflow_metrics(json_clean(m), "D", "dnn[paper]")
    assert flat["test/kld_fou_mean"] == pytest.approx(m["test"]["D"]["dnn[paper]"]["kld_fou_mean"])
    assert "test/kld_fou_mean_ci_lo" in flat and not any(k.startswith("test_") for k in flat)
    table = ev.methods_table(json_clean(m), "D").set_index("method")
    assert table.loc["dnn", "kld_fou_mean_ci_lo"] == pytest.approx(
        m["test"]["D"]["dnn"]["kld_fou_mean_ci"]["lo"]
    )
    assert "registered+network" in table.index and "dice_occ" in table.columns
    assert not any(k.startswith("cross_") for k in flat)
    # plot data and figures show the variant rows where they exist; the box plot is KLD(b)
    from traffictwin.evidential.noise import PoseNoise

    noise = {c: PoseNoise(r=float(i), alpha=float(i)) for i, c in enumerate(data)}
    tables = ev.plot_tables(res, noise)
    assert "dnn[paper]_kld_fou_mean" in tables["fusion_scores"].columns
    assert pd.isna(tables["fusion_scores"].set_index("config").loc["C", "dnn[paper]_kld_fou_mean"])
    panels, meta = ev.figure_inputs(res, noise, grid, 0, 0.5)
    assert meta["configs"] == list(data) and meta["network_rows"] == list(networks)
    assert panels["network"].shape == (len(data), *raw["label"][0].shape)
    np.testing.assert_array_equal(panels["label"][0], raw["label"][0])
    from traffictwin.fusion.evaluation_figures import evaluation_figures
    from traffictwin.report.plot_data import fusion_scores_long

    scores = fusion_scores_long(tables["fusion_scores"])
    figs = evaluation_figures(tables["fusion_kld"], scores, json_clean(res.metrics), panels, meta)
    ax = figs["fusion_kld_boxplot"].axes[0]
    boxes = {p.get_gid(): p for p in ax.patches if p.get_gid()}
    assert (
        "dnn[paper]/D" in boxes and "dnn[paper]/C" not in boxes and "registered+network/C" in boxes
    )
    y = boxes["dnn[paper]/D"].get_path().vertices[:, 1]
    kb = s[(s.config == "D") & (s.method == "dnn[paper]")].kld_fou
    assert (y.min(), y.max()) == pytest.approx(tuple(np.quantile(kb, [0.25, 0.75])))
    assert ax.get_ylabel().startswith("KLD(b)")
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    assert "network (own config) [paper loss]" in legend and "registered + network" in legend
    # the score figures: a line per row of the score table, the variants included
    occ = {ln.get_gid() for a in figs["fusion_scores_occupied"].axes for ln in a.get_lines()}
    assert {"dnn", "naive", "dnn[paper]", "registered+network"} <= occ
    import matplotlib.pyplot as plt

    for fig in figs.values():
        plt.close(fig)


@pytest.mark.usefixtures("single_torch_thread")
def test_evaluate_with_the_dnn_row_only_and_bad_rows():
    data, raw, grid = _synthetic(configs=("A", "B"), n=4)
    nets = {"dnn": {c: _tiny_net(0) for c in data}}
    res = ev.evaluate(data, raw, nets, grid, _eval_config(), CI, FUSION)
    assert sorted(res.metrics["test"]["A"]) == sorted(
        ["ego", "naive", "naive-yager", "naive-cautious", "registered", "dnn"]
    )
    t = res.metrics["targets"]
    assert t["kld_ratio_vs_naive"]["status"] == "not evaluated"  # no C, D
    assert t["hybrid_vs_registered"]["status"] == "not evaluated"
    with pytest.raises(ValueError, match="no 'dnn' row"):
        ev.evaluate(data, raw, {"dnn[paper]": nets["dnn"]}, grid, _eval_config(), CI, FUSION)
    with pytest.raises(ValueError, match="'naive' names no registry method that uses a model"):
        ev.evaluate(data, raw, {**nets, "naive": {}}, grid, _eval_config(), CI, FUSION)
    with pytest.raises(ValueError, match=r"configuration\(s\) \['Z'\]"):
        ev.evaluate(data, raw, {"dnn": {"Z": _tiny_net(0)}}, grid, _eval_config(), CI, FUSION)


# -- bad input -------------------------------------------------------------------------------------
def _write_prealigned(root: Path, n: int = 3, hw: int = 32, **override) -> None:
    rng = np.random.default_rng(1)
    arrays = {
        "inputs": np.concatenate([_random_masses(rng, n, hw, hw)] * 2, axis=1),
        "label": _random_masses(rng, n, hw, hw),
        "noise": np.zeros((n, 3)),
        "rel_pose_true": np.zeros((n, 3)),
        "rel_pose_noisy": np.zeros((n, 3)),
        "pair_id": np.arange(n, dtype=np.int64) * 1000,
    }
    arrays.update(override)
    w = DatasetWriter(root, "prealigned", {"unit": 1}, seed=0)
    w.add_shard(0, arrays, split="test", check=False)  # NaN fixtures: valid hash, bad values
    w.finalize()


def test_bad_masses_and_grid_name_the_dataset_and_array(tmp_path):
    grid = GridSpec(32, 32, 0.5)
    _write_prealigned(tmp_path / "ok")
    data, pid = ev.load_test_sets({"A": tmp_path / "ok"}, "test", None, grid)
    assert len(pid) == 3 and data["A"]["inputs"].shape == (3, 4, 32, 32)
    lab = _random_masses(np.random.default_rng(2), 3, 32, 32)
    lab[1, 0, 4, 4] = np.nan
    _write_prealigned(tmp_path / "nan", label=lab)
    with pytest.raises(DatasetError, match=r"nan/shard-00000.npz: array 'label' holds 1 NaN"):
        ev.load_test_sets({"A": tmp_path / "nan"}, "test", None, grid)
    inp = np.concatenate([_random_masses(np.random.default_rng(3), 3, 32, 32)] * 2, axis=1)
    inp[0, 2:, 1, 1] = 0.8  # m_F + m_O = 1.6 in map 2
    _write_prealigned(tmp_path / "simplex", inputs=inp)
    with pytest.raises(
        DatasetError, match=r"array 'inputs' channels 2-3: masses outside the simplex"
    ):
        ev.load_test_sets({"A": tmp_path / "simplex"}, "test", None, grid)
    with pytest.raises(DatasetError, match=r"array 'inputs': grid 32x32 cells, expected 64x32"):
        ev.load_test_sets({"A": tmp_path / "ok"}, "test", None, GridSpec(64, 32, 0.5))


def test_ci_config_is_typed():
    from omegaconf import OmegaConf

    from traffictwin.config import ConfigError

    cfg = OmegaConf.create(yaml.safe_load((ROOT / "params.yaml").read_text()))
    ci = ev.fusion_ci_config(cfg)
    assert ci.n_boot >= 1000 and ci.level == 0.95
    OmegaConf.update(cfg, "evaluation.fusion_ci.n_boot", 10, merge=False)
    with pytest.raises(ConfigError, match="evaluation.fusion_ci.n_boot"):
        ev.fusion_ci_config(cfg)


# -- promotion gate --------------------------------------------------------------------------------
@pytest.mark.usefixtures("single_torch_thread")
def test_gate_evaluator_produces_the_configured_fusion_metric(monkeypatch):
    """conf/registry's fusion gate metric (KLD(b)) is one of the numbers gate_eval computes."""
    from traffictwin.fusion import metrics as fm
    from traffictwin.fusion.gate_eval import fusion_evaluator
    from traffictwin.fusion.model_io import predict_masses
    from traffictwin.mlops import registry

    params = yaml.safe_load((ROOT / "params.yaml").read_text())
    gate = params["registry"]["fusion"]
    assert (gate["metric"], gate["mode"], gate["split"]) == ("val/kld_fou_mean", "min", "val")
    data, _, _ = _synthetic(configs=("A",), n=3)
    net = _tiny_net(0)
    monkeypatch.setattr(registry, "load_registered", lambda uri, loader, **kw: net)
    out = fusion_evaluator(data["A"]["inputs"], data["A"]["label"], batch_size=2)("models:/x/1")
    pred, _ = predict_masses(net, data["A"]["inputs"], 2)
    assert out[gate["metric"]] == pytest.approx(fm.kld_fou(data["A"]["label"], pred).mean())


def test_learning_curve_figures_are_claimed_and_captioned(tmp_path):
    """The network's and the registration's learning curves have their captions; a loss
    variant's (train_fusion_<name>) is claimed by the fusion section's pattern."""
    from traffictwin.fusion import report_section as rs
    from traffictwin.report.render import collect_figures

    (tmp_path / "figures").mkdir()
    for stem in ("train_registration", "train_fusion_d_paper", "train_fusion_network"):
        (tmp_path / "figures" / f"{stem}.png").write_bytes(b"\x89PNG")
    (figs,), other = collect_figures(tmp_path, [rs.provider({})])
    assert other == [] and [f.path for f in figs] == [
        "figures/train_fusion_network.png",
        "figures/train_registration.png",
        "figures/train_fusion_d_paper.png",
    ]
    assert figs[0].caption.startswith("Learning curves of the fusion network (")
    assert figs[1].caption.startswith("Learning curves of the learned registration (")
    assert figs[2].caption == "`figures/train_fusion_d_paper.png`"


# -- stage: networks per row ---------------------------------------------------------------------
def test_stage_loads_one_row_per_variant(monkeypatch, tmp_path):
    """models/fusion/network fills row dnn at every configuration; each fusion_variants entry its
    row (a mixed-noise variant at every configuration, a per-configuration one at its own);
    fusion_model.loss.name is needed only when there are variants."""
    from omegaconf import OmegaConf

    import pipelines.evaluate_fusion as stage
    from traffictwin.config import ConfigError
    from traffictwin.fusion import model_io

    loaded = []

    def fake_load(path, **kw):
        loaded.append((Path(path).relative_to(tmp_path).as_posix(), kw.get("expected_cfg")))
        return Path(path).parent.name

    monkeypatch.setattr(stage, "fusion_model_dir", lambda name="network": tmp_path / name)
    monkeypatch.setattr(model_io, "load_fusion_model", fake_load)
    cfg = OmegaConf.create(
        {
            "configurations": {"A": {"r": 0.0, "alpha": 0.0}, "D": {"r": 3.0, "alpha": 10.0}},
            "fusion_data": {
                "register": {
                    "configurations": ["mixed"],
                    "max_train_pairs": 8,
                    "max_val_pairs": None,
                }
            },
            "fusion_variants": {},
        }
    )
    nets, runs = stage.load_networks(cfg, ["A", "D"], None, "cpu")  # no fusion_model.loss needed
    # the one network: row dnn, and on registered pairs row registered+network
    assert nets == {
        "dnn": {"A": "network", "D": "network"},
        "registered+network": {"A": "network", "D": "network"},
    }
    assert runs == [
        (tmp_path / "network", "A", "dnn", "train_fusion"),
        (tmp_path / "network", "D", "dnn", "train_fusion"),
        (tmp_path / "network", "A", "registered+network", "train_fusion"),
        (tmp_path / "network", "D", "registered+network", "train_fusion"),
    ]
    assert loaded == [("network/model.ckpt", "mixed")]  # loaded once, trained on the mixture
    cfg.fusion_variants = {
        "paper": {"config": "mixed", "inputs": "prealigned", "loss": "paper"},
        "registered": {"config": "mixed", "inputs": "registered", "loss": None},
        "D": {"config": "D", "inputs": "prealigned", "loss": None},
    }
    cfg.fusion_model = {"loss": {"name": "mass"}}
    nets, runs = stage.load_networks(cfg, ["A", "D"], None, "cpu")
    assert nets == {
        "dnn": {"A": "network", "D": "network"},
        "registered+network": {"A": "network", "D": "network"},
        "dnn[paper]": {"A": "paper", "D": "paper"},
        "registered+network[registered-trained]": {"A": "registered", "D": "registered"},
        "dnn[per-config]": {"D": "D"},
    }
    assert runs[4:] == [
        (tmp_path / "paper", "A", "dnn[paper]", "train_fusion_variant@paper"),
        (tmp_path / "paper", "D", "dnn[paper]", "train_fusion_variant@paper"),
        (
            tmp_path / "registered",
            "A",
            "registered+network[registered-trained]",
            "train_fusion_variant@registered",
        ),
        (
            tmp_path / "registered",
            "D",
            "registered+network[registered-trained]",
            "train_fusion_variant@registered",
        ),
        (tmp_path / "D", "D", "dnn[per-config]", "train_fusion_variant@D"),
    ]
    assert loaded[-1] == ("D/model.ckpt", "D")  # a per-configuration network records its own
    # the learned registration: row learned everywhere, learned+network where a registered-pairs network is
    from traffictwin.fusion import registration_io

    monkeypatch.setattr(stage, "registration_model_dir", lambda: tmp_path / "reg" / "learned")
    monkeypatch.setattr(
        registration_io,
        "load_registration_model",
        lambda path, **kw: f"reg-{kw['expected_cfg']}",
    )
    cfg.registration_model = {"train": {}}
    nets, runs = stage.load_networks(cfg, ["A", "D"], None, "cpu")
    assert nets["learned"] == {"A": "reg-mixed", "D": "reg-mixed"}
    # learned+network: the learned registration with the one network as fusion head
    assert nets["learned+network"] == {"A": ("reg-mixed", "network"), "D": ("reg-mixed", "network")}
    assert runs[-2:] == [
        (tmp_path / "reg" / "learned", "A", "learned", "train_registration"),
        (tmp_path / "reg" / "learned", "D", "learned", "train_registration"),
    ]
    del cfg.registration_model
    cfg.fusion_variants = {
        "D": {"config": "D", "inputs": "prealigned", "loss": None},
        "D2": {"config": "D", "inputs": "prealigned", "loss": "mass"},
    }
    with pytest.raises(
        ConfigError, match=r"fusion_variants.D2' is row 'dnn\[per-config\]' at configuration D"
    ):
        stage.load_networks(cfg, ["A", "D"], None, "cpu")


def test_auroc_with_counts_by_hand_and_too_few_wrong_cells():
    from traffictwin.fusion.metrics import auroc_with_counts

    # two pairs, 4 bins of u: wrong cells at bins 2, 2 | 3; right cells at bins 0, 1 | 2
    pos = np.array([[0, 0, 2, 0], [0, 0, 0, 1]])
    neg = np.array([[1, 1, 0, 0], [0, 0, 1, 0]])
    # each wrong cell in bin 2 beats 2 right cells and ties 1 (2.5); the one in bin 3 beats 3
    r = auroc_with_counts(pos, neg, min_wrong=3, min_pairs=2)
    assert r["u_auroc"] == pytest.approx((2.5 + 2.5 + 3) / 9)
    assert (r["u_auroc_n_wrong"], r["u_auroc_n_right"], r["u_auroc_pairs_wrong"]) == (3, 3, 2)
    assert r["u_auroc_enough"] is True
    # too few wrong cells, or wrong cells in too few pairs: counts kept, no number
    for kw in ({"min_wrong": 4, "min_pairs": 2}, {"min_wrong": 3, "min_pairs": 3}):
        r = auroc_with_counts(pos, neg, **kw)
        assert not r["u_auroc_enough"] and math.isnan(r["u_auroc"]) and r["u_auroc_n_wrong"] == 3
    # no right cell: undefined
    assert not auroc_with_counts(pos, 0 * neg, 1, 1)["u_auroc_enough"]
    with pytest.raises(ValueError, match="differ"):
        auroc_with_counts(pos, neg[:, :3])


def test_the_auroc_target_says_too_few_wrong_cells():
    pid, own = _hand_rows()
    metrics = {"test": {c: {} for c in ("A", "C", "D")}, "diff": {}}
    for (c, row), f in own.items():
        iv = ev.row_intervals(f, np.zeros((5, 4)), np.zeros((5, 4)), CI)
        metrics["test"][c][row] = (
            {k: iv[k].estimate for k in ev.CI_KEYS}
            | {f"{k}_ci": lohi(iv[k]) for k in ev.CI_KEYS}
            | {"u_auroc_enough": False, "u_auroc_n_wrong": 12, "u_auroc_pairs_wrong": 3}
        )
    v = ev.fusion_targets(own, metrics, CI, 0.5, 1.0, FUSION)["u_auroc"]["per_config"]["D"]
    assert v["status"] == "not evaluated"
    assert "too few wrong cells: 12 wrong cells in 3 pairs" in v["why"]


@pytest.mark.usefixtures("single_torch_thread")
def test_evaluate_reports_the_cells_behind_each_auroc():
    data, raw, grid = _synthetic(configs=("A",), n=6)
    nets = {"dnn": {"A": _tiny_net(0)}}
    fc = dataclasses.replace(_eval_config(), auroc_min_wrong=1, auroc_min_pairs=1)
    m = ev.evaluate(data, raw, nets, grid, fc, CI, FUSION).metrics["test"]["A"]
    naive, dnn = m["naive"], m["dnn"]
    # naive = Dempster of the inputs = the label: no wrong cell, so no AUROC
    assert naive["u_auroc_n_wrong"] == 0 and not naive["u_auroc_enough"]
    assert math.isnan(naive["u_auroc"]) and math.isnan(naive["u_auroc_ci"]["lo"])
    # an untrained network is wrong somewhere: counts and a number
    assert dnn["u_auroc_n_wrong"] > 0 and dnn["u_auroc_n_right"] > 0 and dnn["u_auroc_enough"]
    assert 0 <= dnn["u_auroc"] <= 1
    fc = dataclasses.replace(fc, auroc_min_wrong=dnn["u_auroc_n_wrong"] + 1)
    again = ev.evaluate(data, raw, nets, grid, fc, CI, FUSION).metrics["test"]["A"]["dnn"]
    assert not again["u_auroc_enough"] and math.isnan(again["u_auroc"])
    assert again["u_auroc_n_wrong"] == dnn["u_auroc_n_wrong"]
