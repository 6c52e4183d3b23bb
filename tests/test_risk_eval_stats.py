"""Risk evaluation statistics: speed-only baseline, sequence bootstrap of every metric,
paired differences, seed means, targets, collapse flag, critical shares, claims and the ROC figure."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from _acceptance import thresholds
from _report_pages import all_md, page_md
from test_risk_training import SUBJECT_LENGTH, camera_intrinsics, render_frame, thw_risk

from traffictwin.acceptance import Threshold
from traffictwin.io.shards import DatasetWriter
from traffictwin.risk.baselines import GeometricParams, fit_speed_only
from traffictwin.risk.dave2 import Dave2, Dave2Config
from traffictwin.risk.evaluation import (
    SEED_MEAN,
    TARGET_NAMES,
    CIConfig,
    ClusterBootstrap,
    SuiteSettings,
    bootstrap_scores,
    critical_shares,
    difference_of_scores,
    evaluate,
    evaluate_suite,
    judge,
    mean_of_scores,
    roc_auc,
    spread_stat,
    variant_groups,
)
from traffictwin.risk.findings import beats, findings
from traffictwin.risk.model_io import load_risk_model, save_risk_model
from traffictwin.risk.predictor import RiskPredictor
from traffictwin.risk.training import RiskSource
from traffictwin.stats import Interval, mean_ci, resample_counts

RISK = thresholds("risk")  # acceptance.risk

# --------------------------------------------------------------------------------------------
# speed-only baseline
# --------------------------------------------------------------------------------------------


def test_speed_only_is_the_isotonic_fit_by_hand() -> None:
    # PAVA: 0.3 > 0.2 at speeds 2 and 3 are pooled to 0.25
    m = fit_speed_only(np.array([1.0, 2.0, 3.0, 4.0]), np.array([0.1, 0.3, 0.2, 0.5]))
    assert m.speed_knots.tolist() == [1.0, 2.0, 3.0, 4.0]
    assert np.allclose(m.risk_knots, [0.1, 0.25, 0.25, 0.5])
    # linear between knots, constant outside the training speeds
    assert np.allclose(m.predict(np.array([0.0, 2.5, 3.5, 10.0])), [0.1, 0.25, 0.375, 0.5])
    # first crossing of 0.2: between 1 m/s (0.1) and 2 m/s (0.25) -> 1 + 0.1 / 0.15 m/s
    assert m.critical_speed(0.2) == pytest.approx(1 + 0.1 / 0.15)
    assert m.critical_speed(0.05) == 1.0 and math.isinf(m.critical_speed(0.9))
    # repeated speeds are averaged first: (0 + 0.2) / 2 at 1 m/s, then pooled with 0.1 at 2 m/s
    m2 = fit_speed_only(np.array([3.0, 1.0, 1.0, 2.0]), np.array([0.3, 0.0, 0.2, 0.1]))
    assert np.allclose(m2.predict(np.array([1.0, 2.0, 3.0])), [0.1, 0.1, 0.3])
    with pytest.raises(ValueError, match="training split is empty"):
        fit_speed_only(np.zeros(0), np.zeros(0))
    with pytest.raises(ValueError, match="2 speeds but 3 labels"):
        fit_speed_only(np.zeros(2), np.zeros(3))
    with pytest.raises(ValueError, match="finite"):
        m.predict(np.array([np.nan]))


def test_speed_only_monotone_and_recovers_a_function_of_speed() -> None:
    rng = np.random.default_rng(0)
    v = rng.uniform(0, 30, 500)
    y = np.minimum(v / 30.0, 1.0) ** 2  # a label that is a monotone function of speed
    m = fit_speed_only(v, y)
    grid = np.linspace(0, 30, 200)
    p = m.predict(grid)
    assert np.all(np.diff(p) >= -1e-12)
    assert np.max(np.abs(m.predict(v) - y)) < 0.02


# --------------------------------------------------------------------------------------------
# the sequence bootstrap
# --------------------------------------------------------------------------------------------


def _sample(n_seq: int = 12, per: int = 10, seed: int = 0):
    rng = np.random.default_rng(seed)
    clusters = np.repeat(np.arange(n_seq) * 7 + 3, per)  # arbitrary sequence ids
    y = np.clip(rng.gamma(0.8, 0.05, clusters.size), 0, 1)
    p = np.clip(y + rng.normal(0, 0.03, y.size), 0, 1)
    return clusters, y, p


def test_estimates_equal_the_point_metrics() -> None:
    clusters, y, p = _sample()
    plan = ClusterBootstrap(clusters, n_boot=200, seed=1)
    sc = bootstrap_scores(y, p, plan, (1.5, 1.0), 10.0)
    ref = evaluate(y, p, (1.5, 1.0), 10.0)
    for k, (est, boot) in sc.items():
        sec, _, name = k.rpartition("|")
        want = ref[sec][name] if sec else ref[name]
        assert est == pytest.approx(want, abs=1e-12), k
        assert boot.shape == (200,)
    assert sc["at_1.5s|roc_auc"][0] == pytest.approx(roc_auc(y > 1 / 30, p))


def test_mse_interval_is_the_shared_cluster_mean_ci() -> None:
    clusters, y, p = _sample()
    plan = ClusterBootstrap(clusters, n_boot=500, seed=3)
    iv = plan.interval(bootstrap_scores(y, p, plan, (1.5, 1.0))["test/mse"])
    ref = mean_ci((p - y) ** 2, clusters, n_boot=500, seed=3)
    assert (iv.estimate, iv.lo, iv.hi) == pytest.approx((ref.estimate, ref.lo, ref.hi))
    assert iv.n_groups == 12 and np.array_equal(plan.draws, resample_counts(12, 500, 3))


def test_one_resample_by_hand() -> None:
    """Two sequences; the resample drawing sequence 0 twice and 1 never is sequence 0 twice."""
    clusters = np.array([5, 5, 9])
    y = np.array([0.5, 0.0, 0.2])
    p = np.array([0.4, 0.1, 0.0])
    plan = ClusterBootstrap(clusters, n_boot=4, seed=0)
    plan.draws = np.array([[2.0, 0.0], [0.0, 2.0], [1.0, 1.0], [1.0, 3.0]])
    sc = bootstrap_scores(y, p, plan, (1.5,))
    # squared errors: 0.01, 0.01 (sequence 5), 0.04 (sequence 9)
    assert np.allclose(sc["test/mse"][1], [0.01, 0.04, 0.06 / 3, (0.02 + 3 * 0.04) / 5])
    # at 1.5 s: frame 0 TP, frame 1 TN (0.1 > 1/30 is FP? 0.1 > 0.0333: yes, FP), frame 2 FN
    assert np.allclose(sc["at_1.5s|accuracy"][1], [0.5, 0.0, 1 / 3, 1 / 5])
    # recall: sequence 5 has TP, sequence 9 FN; drawing only 5: 1; only 9: 0; once each: 1/2
    assert np.allclose(sc["at_1.5s|recall"][1], [1.0, 0.0, 0.5, 0.25])
    # specificity: the only negative (frame 1) is in sequence 5 and a false positive
    assert sc["at_1.5s|specificity"][1][0] == 0.0 and np.isnan(sc["at_1.5s|specificity"][1][1])
    # AUC: positives 0.4 (seq 5), 0.0 (seq 9); negative 0.1 (seq 5). Drawn (1, 3): pairs weighted
    # 1·1 (0.4 > 0.1) and 3·1 (0.0 < 0.1) -> 1 / 4
    auc = sc["at_1.5s|roc_auc"][1]
    assert auc[0] == 1.0 and np.isnan(auc[1]) and auc[2] == 0.5 and auc[3] == pytest.approx(0.25)


def test_auc_resamples_equal_the_auc_of_the_replicated_frames() -> None:
    clusters, y, p = _sample(n_seq=8, per=6, seed=4)
    p = np.round(p, 2)  # ties
    plan = ClusterBootstrap(clusters, n_boot=20, seed=5)
    boot = bootstrap_scores(y, p, plan, (1.5,))["at_1.5s|roc_auc"][1]
    for b in range(5):
        idx = np.concatenate(
            [
                np.flatnonzero(plan.codes == g).repeat(1)
                for g in range(8)
                for _ in range(int(plan.draws[b, g]))
            ]
        )
        assert boot[b] == pytest.approx(roc_auc(y[idx] > 1 / 30, p[idx]))


def test_perfect_predictor_and_self_difference() -> None:
    clusters, y, _ = _sample()
    plan = ClusterBootstrap(clusters, n_boot=300)
    sc = bootstrap_scores(y, y, plan, (1.5, 1.0))
    for k in ("at_1.5s|roc_auc", "at_1.5s|accuracy", "at_1.5s|balanced_accuracy", "at_1.5s|f1"):
        iv = plan.interval(sc[k])
        assert (iv.estimate, iv.lo, iv.hi) == (1.0, 1.0, 1.0), k
    iv = plan.interval(sc["test/mse"])
    assert (iv.estimate, iv.lo, iv.hi) == (0.0, 0.0, 0.0)
    _, _, p = _sample()
    other = bootstrap_scores(y, p, plan, (1.5, 1.0))
    for k, st in difference_of_scores(other, other).items():
        assert st[0] == 0 and not np.any(st[1][np.isfinite(st[1])]), k
    # paired difference = the difference of the two predictors' values on each resample
    d = difference_of_scores(sc, other)["at_1.5s|roc_auc"]
    assert np.allclose(d[1], sc["at_1.5s|roc_auc"][1] - other["at_1.5s|roc_auc"][1])
    assert d[0] > 0 and plan.interval(d).lo > 0  # the perfect predictor ranks better


def test_seed_mean_averages_the_metric_inside_each_resample() -> None:
    clusters, y, p = _sample()
    plan = ClusterBootstrap(clusters, n_boot=100)
    a, b = (
        bootstrap_scores(y, p, plan, (1.5, 1.0)),
        bootstrap_scores(y, np.clip(p * 0.9, 0, 1), plan, (1.5, 1.0)),
    )
    m = mean_of_scores([a, b])
    for k in a:
        assert m[k][0] == pytest.approx((a[k][0] + b[k][0]) / 2)
        assert np.allclose(m[k][1], (a[k][1] + b[k][1]) / 2, equal_nan=True)
    same = mean_of_scores([a, a])
    assert all(np.allclose(same[k][1], a[k][1], equal_nan=True) for k in a)


def test_subset_and_spread() -> None:
    clusters, y, p = _sample()
    plan = ClusterBootstrap(clusters, n_boot=100)
    sub = plan.subset(clusters < 30)
    assert sub.n_groups == 4 and sub.n == 40
    est, boot = spread_stat(p, plan)
    assert est == pytest.approx(np.std(p))
    assert spread_stat(np.full(p.size, 0.3), plan)[0] == pytest.approx(0.0, abs=1e-9)
    assert np.all(boot > 0)
    with pytest.raises(ValueError, match="no test frames"):
        ClusterBootstrap(np.zeros(0))
    with pytest.raises(ValueError, match="predictions for a plan"):
        bootstrap_scores(y[:5], p[:5], plan, (1.5, 1.0))


# --------------------------------------------------------------------------------------------
# targets, groups, shares, claims
# --------------------------------------------------------------------------------------------


def test_judge_hand_cases() -> None:
    t = Threshold(">=", 0.90, name="bal acc", metric="balanced_accuracy")
    assert judge(Interval(0.92, 0.88, 0.95), t) | {} == {
        "value": 0.92,
        "lo": 0.88,
        "hi": 0.95,
        "threshold": 0.9,
        "op": ">=",
        "met": True,
        "ci_beyond_threshold": False,
    }
    assert judge(Interval(0.85, 0.80, 0.89), t)["met"] is False
    mse = Threshold("<=", 0.01, name="mse", metric="mse")
    assert judge(Interval(0.008, 0.006, 0.0099), mse)["ci_beyond_threshold"] is True
    vs = RISK["auc_vs_speed_only"]  # needs the interval wholly above 0
    assert judge(Interval(0.03, -0.01, 0.07), vs)["met"] is False
    assert judge(Interval(0.03, 0.01, 0.05), vs)["met"] is True
    assert judge(Interval(math.nan, math.nan, math.nan), t)["met"] is False


def test_variant_groups_follow_replicate_of() -> None:
    names = ["headline", "rgbd", "headline_s1", "headline_s2", "paper"]
    rep = {"headline_s1": "headline", "headline_s2": "headline_s1"}  # a chain resolves to the root
    g = variant_groups(names, rep)
    assert g == {
        "headline": ["headline", "headline_s1", "headline_s2"],
        "rgbd": ["rgbd"],
        "paper": ["paper"],
    }
    # replicates of a variant that is not evaluated form its group
    assert variant_groups(["a_s1", "a_s2"], {"a_s1": "a", "a_s2": "a"}) == {"a": ["a_s1", "a_s2"]}
    with pytest.raises(ValueError, match="cycle"):
        variant_groups(["a", "b"], {"a": "b", "b": "a"})


def test_critical_shares_by_hand() -> None:
    f = pd.DataFrame(
        {
            "split": ["train", "train", "train", "test"],
            "scenario": [0, 0, 1, 2],
            "risk_thw_corridor": [0.5, 0.0, 0.0, 0.04],
            "risk_thw_paper": [0.5, 0.5, 0.04, 0.0],
        }
    )
    cs = critical_shares(f, ["risk_thw_corridor", "risk_thw_paper", "risk_thw_fov"], 1.5)
    tr = cs["splits"]["train"]
    assert tr == {
        "n_frames": 3,
        "n_sequences": 2,
        "risk_thw_corridor": pytest.approx(1 / 3),
        "risk_thw_paper": 1.0,
    }
    assert cs["splits"]["test"]["risk_thw_corridor"] == 1.0
    assert cs["splits"]["val"] == {"n_frames": 0, "n_sequences": 0}
    assert cs["splits"]["all"]["risk_thw_paper"] == 0.75


def test_claims_only_when_the_interval_excludes_zero() -> None:
    d = {
        "at_1.5s": {"roc_auc": {"estimate": 0.05, "lo": 0.02, "hi": 0.08}},
        "test/mse": {"estimate": 0.002, "lo": -0.001, "hi": 0.004},
    }
    assert beats(d, "at_1.5s.roc_auc") is True  # higher ROC-AUC: a better
    assert beats(d, "test/mse") is None  # the interval covers 0: no claim
    d["test/mse"] = {"estimate": 0.002, "lo": 0.001, "hi": 0.004}  # higher MSE: worse
    assert beats(d, "test/mse") is False
    d["test/mse"] = {"estimate": -0.002, "lo": -0.004, "hi": -0.001}  # lower MSE: better
    assert beats(d, "test/mse") is True
    d["at_1.5s"]["roc_auc"] = {"estimate": 0.0, "lo": 0.0, "hi": 0.08}  # touching 0: no claim
    assert beats(d, "at_1.5s.roc_auc") is None
    assert beats({}, "test/mse") is None and beats(None, "test/mse") is None
    assert beats({"test/mse": {"estimate": 1.0, "lo": None, "hi": 2.0}}, "test/mse") is None


def test_roc_points_area_is_the_auc_of_the_metrics_and_of_sklearn() -> None:
    from sklearn.metrics import roc_auc_score

    from traffictwin.risk.charts import roc_points

    _, y, p = _sample(seed=9)
    p = np.round(p, 2)  # ties
    pos = y > 1 / 30
    fpr, tpr = roc_points(pos, p)
    assert fpr[0] == tpr[0] == 0 and fpr[-1] == tpr[-1] == 1
    assert np.all(np.diff(fpr) >= 0) and np.all(np.diff(tpr) >= 0)
    area = float(np.sum(np.diff(fpr) * (tpr[1:] + tpr[:-1]) / 2))
    assert area == pytest.approx(roc_auc(pos, p), rel=1e-12)
    assert area == pytest.approx(roc_auc_score(pos, p), rel=1e-12)


def test_plot_roc_draws_each_predictor(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from traffictwin.risk import figures

    figs: dict = {}
    monkeypatch.setattr(
        figures, "save_figure", lambda fig, path, **_: figs.__setitem__(Path(path).name, fig)
    )
    pos = np.array([1, 0, 1, 0], bool)
    scores = {"net": np.array([0.9, 0.5, 0.5, 0.1]), "geometric_gt": np.array([0.1, 0.9, 0.5, 0.2])}
    figures.plot_roc(pos, scores, tmp_path / "r.png", auc={"net": 0.875, "geometric_gt": None})
    ax = figs["r.png"].axes[0]
    lines = {ln.get_label(): ln for ln in ax.lines}
    assert set(lines) == {"net (AUC 0.875)", "geometric_gt", "chance"}
    net = lines["net (AUC 0.875)"]
    assert net.get_xdata().tolist() == [0, 0, 0.5, 1] and net.get_ydata().tolist() == [0, 0.5, 1, 1]
    assert lines["geometric_gt"].get_linestyle() == "--"  # the oracle dashed
    assert "false positive rate" in ax.get_xlabel() and "true positive rate" in ax.get_ylabel()


# --------------------------------------------------------------------------------------------
# the whole suite on synthetic data with several test sequences
# --------------------------------------------------------------------------------------------

SITUATIONS = ("follow_close", "free", "cut_in")


def write_sequences(repo: Path, n_shards: int = 5, per_shard: int = 24, seq_len: int = 3) -> None:
    """data/risk + data/disparity (+ orb.csv, every pair passes) with several sequences per shard
    (scenario = frame_id // seq_len); shards 0..n-3 train, n-2 val, n-1 test. Labels from the exact
    geometry: corridor = fov = the box ahead, paper also a vehicle beside the subject at times."""
    rng = np.random.default_rng(0)
    cam = camera_intrinsics(96, 48)
    rw = DatasetWriter(repo / "data" / "risk", "risk", {"synthetic": True}, 0)
    dw = DatasetWriter(repo / "data" / "disparity", "disparity", {"synthetic": True}, 0)
    rows = []
    for s in range(n_shards):
        split = "test" if s == n_shards - 1 else "val" if s == n_shards - 2 else "train"
        lefts, gts, sgms = [], [], []
        for i in range(per_shard):
            fid = s * per_shard + i
            speed = float(rng.uniform(3, 25))
            depth = float(rng.uniform(2.0, 35.0)) if rng.random() < 0.8 else None
            gt, left = render_frame(cam, depth, rng=rng)
            sgm = gt + rng.normal(0, 0.2, gt.shape).astype(np.float32)
            sgm[(gt <= 0) | (rng.random(gt.shape) < 0.1)] = -1.0
            dist = (depth + cam["mount_x"] - SUBJECT_LENGTH / 2) if depth is not None else np.inf
            r = float(thw_risk(np.array(dist / speed)))
            r_paper = max(r, float(thw_risk(np.array(1.0 / speed)))) if rng.random() < 0.2 else r
            scen = fid // seq_len
            rows.append(
                dict(
                    frame_id=fid,
                    shard=s,
                    idx=i,
                    scenario=scen,
                    split=split,
                    situation=SITUATIONS[scen % 3],
                    t=0.1 * i,
                    speed=speed,
                    thw=dist / speed,
                    risk=r,
                    risk_thw_corridor=r,
                    risk_thw_paper=r_paper,
                    risk_thw_fov=r,
                    fault="none",
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
    rw.add_table("frames.csv", pd.DataFrame(rows))
    rw.finalize({"camera": cam})
    dw.finalize()


class FakeModel(RiskPredictor):
    """A risk model stand-in (``cfg``, ``meta``, ``predict_frames``): the geometric risk of the
    disparity it reads plus seeded noise, clipped to [0, 1]; ``noise=None``: one output for every
    frame."""

    def __init__(self, inputs, speed, meta, noise: float | None, seed: int) -> None:
        self.cfg = Dave2Config(inputs=inputs, use_speed=speed)
        self.meta = meta
        self.noise, self.rng = noise, np.random.default_rng(seed)
        self.geo = GeometricParams(subject_length=SUBJECT_LENGTH, subject_width=1.8)

    def predict_frames(self, frames, batch_size) -> np.ndarray:
        from traffictwin.risk.baselines import geometric_risk

        if self.noise is None:
            return np.full(len(frames.left_bgr), 0.1, np.float32)
        key = "disp_sgm" if "disp_sgm" in self.cfg.inputs else "disp_gt"
        disp = frames.disp(key, "fake model")
        v = frames.speed if self.cfg.use_speed else np.full(len(disp), 12.0, np.float32)
        _, _, r = geometric_risk(disp, v, camera_intrinsics(96, 48), self.geo)
        return np.clip(r + self.rng.normal(0, self.noise, r.shape), 0, 1).astype(np.float32)


def _models() -> dict:
    """headline (+ two seeds, one collapsed), rgbd (no speed), paper (other label), log-THW objective."""
    spec = [
        ("headline", ("rgb", "disp_sgm"), True, "risk_thw_corridor", "mse", 0.02),
        ("headline_s1", ("rgb", "disp_sgm"), True, "risk_thw_corridor", "mse", 0.03),
        ("headline_s2", ("rgb", "disp_sgm"), True, "risk_thw_corridor", "mse", None),
        ("rgbd", ("rgb", "disp_sgm"), False, "risk_thw_corridor", "mse", 0.05),
        ("headline_logthw", ("rgb", "disp_sgm"), True, "risk_thw_corridor", "log_thw", 0.02),
        ("paper", ("rgb", "disp_sgm"), False, "risk_thw_paper", "mse", 0.05),
    ]
    return {
        name: FakeModel(inputs, speed, {"label": lab, "variant": name, "objective": obj}, noise, i)
        for i, (name, inputs, speed, lab, obj, noise) in enumerate(spec)
    }


def test_real_models_load_and_evaluate(tmp_path: Path) -> None:
    """The suite runs real saved Dave2 models too (their meta gives label and objective)."""
    write_sequences(tmp_path, n_shards=3, per_shard=6)
    torch.manual_seed(0)
    save_risk_model(
        Dave2(Dave2Config(inputs=("rgb", "disp_sgm"), use_speed=True)),
        tmp_path / "m",
        {"label": "risk_thw_corridor", "objective": "mse"},
    )
    src = RiskSource(tmp_path / "data" / "risk", tmp_path / "data" / "disparity", None)
    metrics, _ = evaluate_suite(
        src,
        {"m": load_risk_model(tmp_path / "m")},
        SuiteSettings(
            acceptance=RISK,
            thresholds_s=(1.5, 1.0),
            primary_label="risk_thw_corridor",
            ci=CIConfig(100, 0, 0.95),
            collapse_std=1e-3,
        ),
    )
    assert metrics["models"]["m"]["label"] == "risk_thw_corridor"
    assert metrics["main_variant"] == "m" and "geometric_sgm" not in metrics["baselines"]
    assert metrics["targets"]["learned_vs_rule_auc"]["met"] is False
    json.dumps(metrics, allow_nan=False)


VARIANTS = {
    "headline_s1": {"replicate_of": "headline", "seed_offset": 1},
    "headline_s2": {"replicate_of": "headline", "seed_offset": 2},
    "headline_logthw": {"objective": "log_thw"},
}


@pytest.fixture(scope="module")
def suite(tmp_path_factory: pytest.TempPathFactory):
    tmp = tmp_path_factory.mktemp("suite")
    write_sequences(tmp)
    src = RiskSource(tmp / "data" / "risk", tmp / "data" / "disparity", None)
    settings = SuiteSettings(
        acceptance=RISK,
        thresholds_s=(1.5, 1.0),
        primary_label="risk_thw_corridor",
        geometric=GeometricParams(subject_length=SUBJECT_LENGTH, subject_width=1.8),
        main_variant="headline",
        variants=VARIANTS,
        ci=CIConfig(300, 0, 0.95),
        collapse_std=1e-3,
    )
    metrics, pred = evaluate_suite(src, _models(), settings)
    return src, metrics, pred


def test_suite_layout_collapse_and_seed_mean(suite) -> None:
    src, metrics, pred = suite
    json.dumps(metrics, allow_nan=False)
    test = src.split_frames("test")
    assert metrics["bootstrap"]["n_clusters"] == test["scenario"].nunique() == 8
    models = metrics["models"]
    assert models["headline_s2"]["collapsed"] is True and models["headline_s2"]["pred_std"] < 1e-3
    assert not any(models[v]["collapsed"] for v in models if v != "headline_s2")
    assert (
        models["headline_logthw"]["objective"] == "log_thw"
        and models["paper"]["label"] == "risk_thw_paper"
    )
    # the collapsed seed is left out of the seed mean
    g = metrics["groups"]["headline"]
    assert g["members"] == ["headline", "headline_s1", "headline_s2"]
    assert g["used"] == ["headline", "headline_s1"] and g["collapsed"] == ["headline_s2"]
    mse = [models[v]["test/mse"] for v in g["used"]]
    assert g["test/mse"] == pytest.approx(np.mean(mse)) and g["n_seeds"] == 2
    assert metrics["main_predictor"] == f"headline{SEED_MEAN}"
    for v, e in models.items():  # every value has an interval around it
        for k in ("test/mse", "test/mae"):
            assert e[f"{k}_ci"]["lo"] <= e[k] <= e[f"{k}_ci"]["hi"], (v, k)
        y = pred[e["label"]].to_numpy()
        assert e["test/mse"] == pytest.approx(np.mean((pred[f"pred_{v}"] - y) ** 2))
    # baselines: on the primary label; the speed-only one also on the paper label (the paper variant)
    assert set(metrics["baselines"]) == {
        "train_mean",
        "train_median",
        "speed_only",
        "geometric_sgm",
        "geometric_gt",
    }
    # GT disparity along a straight corridor: a reference, not an oracle (the label's corridor bends)
    gt = metrics["baselines"]["geometric_gt"]
    assert gt["oracle"] is False and gt["uses_gt_disparity"] is True
    assert set(metrics["baselines_by_label"]) == {"risk_thw_paper"}
    train = src.split_frames("train")
    so = fit_speed_only(train["speed"], train["risk_thw_corridor"])
    assert np.allclose(pred["pred_speed_only"], so.predict(pred["speed"]))


def test_suite_differences_targets_and_breakdowns(suite) -> None:
    _, metrics, pred = suite
    d = metrics["differences"]
    head = f"headline{SEED_MEAN}"
    assert {
        "headline|speed_only",
        "headline_s1|speed_only",
        "headline_s2|speed_only",
        "rgbd|speed_only",
        "paper|speed_only",
        f"{head}|speed_only",
        f"{head}|geometric_sgm",
        f"{head}|geometric_gt",
        f"{head}|rgbd",
        f"{head}|headline_logthw",
    } <= set(d)
    assert (
        d[f"{head}|headline_logthw"]["kind"] == "objective"
        and d[f"{head}|rgbd"]["kind"] == "variant"
    )
    assert d["paper|speed_only"]["label"] == "risk_thw_paper"
    assert not any(k.startswith(f"{head}|paper") for k in d)  # another label: not compared directly
    # the paired difference of the seed mean = seed-mean metric − baseline metric
    m = metrics["models"]
    auc = np.mean([m[v]["at_1.5s"]["roc_auc"] for v in ("headline", "headline_s1")])
    geo = metrics["baselines"]["geometric_sgm"]["at_1.5s"]["roc_auc"]
    assert d[f"{head}|geometric_sgm"]["at_1.5s"]["roc_auc"]["estimate"] == pytest.approx(auc - geo)
    t = metrics["targets"]
    # the balanced-accuracy targets are reported at the first and second thresholds
    per_threshold = {"shipped_balanced_accuracy_primary", "shipped_balanced_accuracy_second"}
    reported = {"shipped_balanced_accuracy_1.5s", "shipped_balanced_accuracy_1s"}
    assert set(t) == (set(TARGET_NAMES) - per_threshold) | reported
    assert t["shipped_balanced_accuracy_1s"]["description"].endswith("at THW 1.0 s")
    # without a shipped / learned predictor (no select_risk) the targets judge the headline
    assert t["shipped_balanced_accuracy_1.5s"]["value"] == pytest.approx(
        metrics["groups"]["headline"]["at_1.5s"]["balanced_accuracy"]
    )
    assert t["learned_vs_rule_auc"]["value"] == pytest.approx(auc - geo)
    assert "test_mse" not in t  # met by a constant: not a target
    assert t["spread"]["met"] is False and t["spread"]["collapsed"] == ["headline_s2"]
    for e in t.values():
        assert isinstance(e["met"], bool)
    # critical share per split and region from frames.csv
    cs = metrics["critical_share"]["splits"]
    assert {"train", "val", "test", "all"} == set(cs)
    assert cs["test"]["risk_thw_corridor"] == pytest.approx(
        float(np.mean(pred["risk_thw_corridor"] > 1 / 30))
    )
    # situations: the headline's recall per situation over that situation's sequences
    sit = metrics["situations"]
    assert set(sit) == set(SITUATIONS)
    e = sit["free"]
    mask = (pred["situation"] == "free").to_numpy()
    y = pred["risk_thw_corridor"].to_numpy()[mask] > 1 / 30
    rec = [
        np.mean(pred[f"pred_{v}"].to_numpy()[mask][y] > 1 / 30) for v in ("headline", "headline_s1")
    ]
    assert e["predictors"][head]["recall"] == pytest.approx(np.mean(rec))
    assert e["n_frames"] == int(mask.sum())
    # region: three labels, predictors incl. the oracle, skill with an interval
    reg = metrics["region"]
    assert set(reg["labels"]) == {"risk_thw_corridor", "risk_thw_paper", "risk_thw_fov"}
    assert len(reg["agreement"]) == 3
    sk = reg["predictors"]["geometric_gt"]["risk_thw_fov"]
    assert sk["skill"] == pytest.approx(
        1 - sk["test/mse"] / reg["predictors"]["train_mean"]["risk_thw_fov"]["test/mse"]
    )
    assert sk["skill_ci"]["lo"] <= sk["skill"] <= sk["skill_ci"]["hi"]
    # networks that differ only in their label's region: paired skill difference (later region
    # − earlier, each on its own label); seeds, other objectives' labels equal: not compared
    sd = reg["skill_differences"]
    assert set(sd) == {"paper|rgbd"}
    p = reg["predictors"]
    want = p["paper"]["risk_thw_paper"]["skill"] - p["rgbd"]["risk_thw_corridor"]["skill"]
    assert sd["paper|rgbd"]["estimate"] == pytest.approx(want)
    assert sd["paper|rgbd"]["lo"] <= want <= sd["paper|rgbd"]["hi"]


def test_findings_never_interpret_a_collapsed_run(suite) -> None:
    _, metrics, _ = suite
    text = findings(metrics)
    assert text.startswith("- **Paper comparison (headline")
    assert "**Failed runs" in text and "headline_s2 (std" in text
    # no sentence claims anything about the collapsed run
    for line in text.splitlines():
        if "headline_s2" in line and "Failed runs" not in line:
            assert "beats" not in line.split("headline_s2")[1][:80]
    assert "oracle" not in text
    assert "**Targets" not in text  # the acceptance table shows them
    # the variants' and baselines' paired differences: the report's tables, not the findings
    assert "Training objectives" not in text and "Baselines on the same frames" not in text
    assert "paper: risk_thw_paper" in text  # another label, named, not compared with the headline
    # the situations, the data and every predictor's scores: the report's tables
    assert "by situation type" not in text and "per region, train / val / test" not in text
    assert "**Data:**" not in text and "test frames, label" not in text
    # every claim of a difference quotes its interval; "beats" only where it excludes zero
    for d in metrics["differences"].values():
        iv = d["at_1.5s"]["roc_auc"]
        if iv["lo"] is not None and iv["lo"] <= 0 <= iv["hi"]:
            assert beats(d, "at_1.5s.roc_auc") is None


def test_findings_of_a_hand_made_metrics_dict() -> None:
    at = {
        "accuracy": 0.8,
        "accuracy_ci": {"lo": 0.7, "hi": 0.9},
        "balanced_accuracy": 0.75,
        "f1": 0.85,
        "roc_auc": 0.9,
        "roc_auc_ci": {"lo": 0.85, "hi": 0.95},
        "critical_fraction_true": 0.6,
    }
    m = {
        "thresholds_s": [1.5, 1.0],
        "main_variant": "net",
        "main_predictor": "net",
        "collapse_std": 1e-3,
        "models": {
            "net": {
                "label": "L",
                "inputs": ["rgb", "disp_sgm"],
                "speed": True,
                "test/mse": 0.01,
                "test/n": 100,
                "at_1.5s": at,
            },
            "dead": {
                "label": "L",
                "inputs": ["rgb"],
                "speed": False,
                "test/mse": 0.05,
                "collapsed": True,
                "pred_std": 0.0,
                "at_1.5s": at,
            },
        },
        "baselines": {
            "speed_only": {
                "at_1.5s": {"roc_auc": 0.8},
                "test/mse": 0.02,
                "critical_speed_at_1.5s": 4.25,
            }
        },
        "differences": {
            "net|speed_only": {
                "a": "net",
                "b": "speed_only",
                "kind": "vs_speed_only",
                "at_1.5s": {"roc_auc": {"estimate": 0.1, "lo": 0.05, "hi": 0.15}},
                "test/mse": {"estimate": -0.01, "lo": -0.02, "hi": 0.001},
            },
            "net|dead": {
                "a": "net",
                "b": "dead",
                "kind": "variant",
                "at_1.5s": {"roc_auc": {"estimate": 0.4, "lo": 0.3, "hi": 0.5}},
            },
        },
    }
    text = findings(m)
    # 0.01 / 0.0147 = 0.680: the test MSE against the paper's (its scores: the results table)
    assert "**Paper comparison (net, label L):** test MSE 0.68× the paper's (below it)" in text
    assert "80.00 %" not in text and "0.900" not in text
    assert "beats speed_only" not in text  # the report's table of paired differences shows it
    assert "every frame above 4.2 m/s critical" in text
    assert "dead (std 0)" in text and "net beats dead" not in text  # collapsed: never interpreted
    assert findings({"models": {}}) == "- No risk network was evaluated."
    # the region: the camera-region network's paired skill difference to the paper-region one
    m["models"]["fov"] = {"label": "risk_thw_fov", "at_1.5s": at}
    fov, paper = "risk_thw_fov", "risk_thw_paper"
    m["region"] = {
        "labels": {
            paper: {"critical_fraction_at_1.5s": 0.8},
            fov: {"critical_fraction_at_1.5s": 0.7},
        },
        "agreement": {f"{paper}|{fov}": {"class_agreement_at_1.5s": 0.9}},
        "skill_differences": {
            "fov|net": {"a": "fov", "b": "net", "label_a": fov, "label_b": paper, "estimate": -0.05}
            | {"lo": -0.08, "hi": -0.02}
        },
    }
    text = findings(m)
    assert "same class on 90.00 % of the test frames (critical share 80.00 % with the" in text
    assert "fov − net skill −0.050 [−0.080, −0.020] (paired): the camera-region label is" in text


def test_stage_config_is_checked() -> None:
    """evaluate_risk reads evaluation.risk (ci, collapse_std) and the variants' replicate_of with
    errors that name the key."""
    import yaml
    from omegaconf import OmegaConf

    from pipelines.evaluate_risk import variant_settings
    from traffictwin.config import ConfigError, typed
    from traffictwin.risk.config import EvalRiskConfig

    root = Path(__file__).resolve().parents[1]
    p = OmegaConf.create(yaml.safe_load((root / "params.yaml").read_text()))
    ev = typed(p.evaluation.risk, EvalRiskConfig, key="evaluation.risk")
    ci = typed(ev.ci, CIConfig, key="evaluation.risk.ci")
    assert (ci.n_boot, ci.seed, ci.level) == (2000, 0, 0.95) and ev.collapse_std == 1e-3
    with pytest.raises(ConfigError, match=r"evaluation\.risk\.ci.*n_boot"):
        typed({"n_boot": 5, "seed": 0, "level": 0.95}, CIConfig, key="evaluation.risk.ci")
    with pytest.raises(ConfigError, match=r"evaluation\.risk\.ci.*level"):
        typed({"n_boot": 500, "seed": 0, "level": 1.5}, CIConfig, key="evaluation.risk.ci")
    bad = OmegaConf.to_container(p.evaluation.risk)
    bad["collapse_std"] = -1.0
    with pytest.raises(ConfigError, match="collapse_std"):
        typed(bad, EvalRiskConfig, key="evaluation.risk")
    names = list(p.risk_model.run_variants)
    assert set(variant_settings(p, names)) == set(names)
    p.risk_model.variants[names[0]]["replicate_of"] = "nope"
    with pytest.raises(ConfigError, match=rf"variants\.{names[0]}\.replicate_of.*'nope'"):
        variant_settings(p, names)


def test_report_section_shows_intervals_differences_and_targets(suite, tmp_path: Path) -> None:
    """The risk section renders risk.json's intervals, differences and targets, the appendix its
    critical shares and situations; every number is traced to its file (the report tests'
    checker)."""
    from test_report import check_report, md_tables, tiny_png

    from pipelines.report import providers
    from traffictwin.report import model as M
    from traffictwin.report import render as R

    _, metrics, _ = suite
    rep = tmp_path / "reports"
    (rep / "metrics").mkdir(parents=True)
    (rep / "figures").mkdir()
    (rep / "metrics" / "risk.json").write_text(json.dumps(metrics, allow_nan=False))
    selection = {  # select_risk's choices on validation (layout of reports/metrics/risk_selection.json)
        "split": "val",
        "n_frames": 24,
        "n_sequences": 8,
        "thresholds_s": [1.5, 1.0],
        "rules": {"geometric_sgm": {"half_width": 1.0}, "geometric_gt": {"half_width": 1.5}},
        "predictors": {
            "geometric_sgm": {
                "kind": "geometric",
                "group": "geometric_sgm",
                "roc_auc": 0.94,
                "decision": {"1.5": {"cut": 0.036, "balanced_accuracy": 0.9}},
            },
            "headline": {
                "kind": "dave2",
                "group": "headline",
                "roc_auc": 0.8,
                "decision": {"1.5": {"cut": 0.027, "balanced_accuracy": 0.74}},
            },
        },
        "shipped": {"predictor": "geometric_sgm", "kind": "geometric"},
    }
    (rep / "metrics" / "risk_selection.json").write_text(json.dumps(selection))
    (rep / "figures" / "risk_roc.png").write_bytes(tiny_png())
    inputs = M.ReportInputs(reports_dir=rep, profile="ci", seed=0, git_commit="c0ffee")
    out = R.write_report(inputs, providers({}))
    check_report(rep, {}, {})
    assert not [m for m in out.missing if "risk.json" in m]
    md = all_md(rep)  # the index and every page, in the order of out.sections
    anchors = [t.anchor for s in out.sections for t in s.tables]
    tables = md_tables(md)
    ci = tables[anchors.index("risk-results")]  # the paper's rows, then every predictor
    head = f"headline{SEED_MEAN}"
    assert [r[0] for r in ci[:2]] == ["paper (Feth et al.)", "Wang & Kato [20]"]
    assert ci[0][4:6] == ["0.0147", "—"] and ci[1][8] == "70.77 %"
    assert ci[2][0] == head and ci[2][2] == "seed mean of 2"
    g = metrics["groups"]["headline"]
    assert ci[2][4] == M.fmt_value(g["test/mse"])
    lo, hi = g["test/mse_ci"]["lo"], g["test/mse_ci"]["hi"]
    assert ci[2][5] == f"[{M.fmt_value(lo)}, {M.fmt_value(hi)}]"
    acc = g["at_1.5s"]["accuracy_ci"]
    assert ci[2][8:10] == [M.fmt_value(g["at_1.5s"]["accuracy"], "pct")] + [
        f"[{M.fmt_value(acc['lo'], 'pct')}, {M.fmt_value(acc['hi'], 'pct')}]"
    ]
    dead = next(r for r in ci if r[0] == "headline_s2")
    assert dead[2] == "collapsed: failed run"
    gt = next(r for r in ci if r[0] == "geometric_gt")
    assert gt[2] == "reference: GT disparity"
    diff = tables[anchors.index("risk-diff")]
    row = next(r for r in diff if r[:2] == [head, "geometric_gt (GT disparity)"])
    d = metrics["differences"][f"{head}|geometric_gt"]["at_1.5s"]["roc_auc"]
    assert row[8] == M.fmt_value(d["estimate"])
    assert (
        row[-1]
        == {True: "a better", False: "b better", None: "no significant difference"}[
            beats(metrics["differences"][f"{head}|geometric_gt"], "at_1.5s.roc_auc")
        ]
    )
    sel = tables[anchors.index("risk-selection")]
    assert [r[0] for r in sel] == ["geometric_sgm", "headline"]  # the shipped one first
    assert sel[0][-1] == "shipped" and sel[1][-1] == "" and sel[0][3] == "0.94"
    assert sel[1][4] == M.fmt_value(0.027, "g4") and sel[1][5] == "74.00 %"
    # the targets: the index's acceptance table (no targets table on the risk page)
    assert "risk-targets" not in anchors
    targets = [r for r in tables[anchors.index("acceptance")] if r[0] == "risk"]
    assert [r[1] for r in targets] == list(metrics["targets"])
    assert next(r for r in targets if r[1] == "spread")[5] == "fail"
    # the region check, the data per split and the situations: risk.json in the appendix
    assert {"risk-region", "risk-data", "risk-situations"}.isdisjoint(anchors)
    appendix = page_md(rep, "appendix")
    s0 = sorted(SITUATIONS)[0]
    p0 = sorted(metrics["situations"][s0]["predictors"])[0]
    recall = metrics["situations"][s0]["predictors"][p0]["recall"]
    assert f"| situations.{s0}.predictors.{p0}.recall | {M.fmt_value(recall)} |" in appendix
    n = M.fmt_value(metrics["critical_share"]["splits"]["test"]["n_frames"], "int")
    assert f"| critical_share.splits.test.n_frames | {n} |" in appendix
    assert "The paper's data (Sec. 3.3, 3.5): 110,152 stereo frames" in page_md(rep, "risk")
    res = (rep / "results_table.md").read_text()  # the headline tables go to docs/results.md
    assert "Risk: test results, paper vs every predictor on the same test frames" in res
    assert "Every target of this run against its acceptance threshold" in res
    assert "(../figures/risk_roc.png)" in page_md(rep, "risk")


def test_critical_errors_follow_the_primary_threshold() -> None:
    """``*_critical_s`` average over the frames below the first of ``thresholds_s`` (the config's
    primary threshold), in the point metrics and in the bootstrap alike. Hand-computed: THW of
    y = [10, 0.5, 0.25, 0.125] s, of p = [0.5, 0.5, 10, 0.125] s, errors [9.5, 0, 9.75, 0] s."""
    y = np.array([0.0, 0.1, 0.2, 0.4])
    p = np.array([0.1, 0.1, 0.0, 0.4])
    assert evaluate(y, p, (1.5, 1.0), 10.0)["test/thw_mae_critical_s"] == pytest.approx(9.75 / 3)
    assert evaluate(y, p, (0.3, 1.5), 10.0)["test/thw_mae_critical_s"] == pytest.approx(9.75 / 2)
    assert evaluate(y, p, (0.3,), 10.0)["test/thw_median_error_critical_s"] == pytest.approx(4.875)
    plan = ClusterBootstrap(np.arange(4), n_boot=20, seed=0)
    sc = bootstrap_scores(y, p, plan, (0.3, 1.5), 10.0)
    assert sc["test/thw_mae_critical_s"][0] == pytest.approx(9.75 / 2)
    with pytest.raises(ValueError, match="at least one THW threshold"):
        evaluate(y, p, (), 10.0)
