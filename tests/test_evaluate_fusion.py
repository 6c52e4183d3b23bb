"""Fusion evaluation: baselines, figures and findings (fast, synthetic) and stage evaluate_fusion on the ci DAG."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from conftest import run_record

from traffictwin.evidential.dempster import dempster
from traffictwin.fusion.evaluation import (
    CI_KEYS,
    DIFF_KEYS,
    JUDGES,
    TIMING_TARGETS,
    EvalSettings,
    evaluate_method,
)
from traffictwin.fusion.findings import fusion_findings
from traffictwin.fusion.methods import METHODS as REGISTRY
from traffictwin.fusion.methods import FusionInput, fuse
from traffictwin.grid import GridSpec

CFGS = ("A", "B", "C", "D")
METHODS = ("ego", "naive", "naive-yager", "naive-cautious", "registered", "dnn")


def random_masses(rng: np.random.Generator, n: int, h: int = 16, w: int = 12) -> np.ndarray:
    d = rng.dirichlet([1.0, 1.0, 1.0], size=(n, h, w))
    return np.moveaxis(d[..., :2], -1, 1).astype(np.float32)


def fuse_prealigned(inputs: np.ndarray, method: str) -> np.ndarray:
    return fuse(method, FusionInput(inputs=inputs)).masses


def png_ok(path: Path) -> None:
    """A valid PNG with content: PNG signature, decodable, several distinct colours."""
    import matplotlib.image as mpimg

    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", path
    img = mpimg.imread(path)
    assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 100, path
    # colours rounded to 0.01 (np.round's rint(x * 100)), each packed into one integer: a
    # row-wise np.unique over every pixel took seconds per figure
    q = np.rint(img[..., :3] * 100).astype(np.int64)
    colours = np.unique((q[..., 0] * 101 + q[..., 1]) * 101 + q[..., 2])
    assert colours.size > 20, f"{path}: (almost) blank image"


# -- library (fast) ---------------------------------------------------------------------------------
def test_prealigned_baselines():
    rng = np.random.default_rng(0)
    m1, m2 = random_masses(rng, 3), random_masses(rng, 3)
    inputs = np.concatenate([m1, m2], axis=1)
    np.testing.assert_array_equal(fuse_prealigned(inputs, "ego"), m1)
    np.testing.assert_allclose(fuse_prealigned(inputs, "naive"), dempster(m1, m2), atol=1e-6)
    c = fuse_prealigned(np.concatenate([m1, m1], axis=1), "naive-cautious")
    np.testing.assert_allclose(c, m1, atol=1e-5)  # idempotent
    with pytest.raises(ValueError, match="unknown fusion method"):
        fuse_prealigned(inputs, "bayes")
    with pytest.raises(ValueError, match="inputs must have shape"):
        fuse_prealigned(m1, "naive")
    with pytest.raises(ValueError, match="needs"):
        fuse("registered", FusionInput(inputs=inputs))


def test_evaluate_prealigned_naive_equals_label_gives_zero_kld():
    rng = np.random.default_rng(1)
    m1, m2 = random_masses(rng, 5), random_masses(rng, 5)
    inputs = np.concatenate([m1, m2], axis=1)
    label = dempster(m1, m2)
    x = FusionInput(inputs=inputs)
    frame, auroc = evaluate_method(
        "naive", x, label, EvalSettings(batch_size=2, success_trans_m=0.5, success_rot_deg=1.0)
    )
    assert len(frame) == 5 and (frame["ms"] >= 0).all()
    np.testing.assert_allclose(frame["kld_fo"], 0, atol=1e-6)
    assert (frame["dice_occ"].fillna(1) == 1).all() and (frame["dice_free"].fillna(1) == 1).all()
    assert auroc.n_wrong == 0 and math.isnan(auroc.value())
    ego, _ = evaluate_method(
        "ego", x, label, EvalSettings(success_trans_m=0.5, success_rot_deg=1.0)
    )
    assert (ego["kld_fo"] > 0).all()


def test_evaluate_registered_on_synthetic_pair():
    from test_registration import render, structured_world

    from traffictwin.evidential.warp import warp_masses
    from traffictwin.fusion.metrics import kld_fo
    from traffictwin.fusion.registration import RegistrationParams
    from traffictwin.geometry import relative_pose

    grid = GridSpec(128, 96, 0.5)
    world, pw = structured_world(1, grid)
    p1, p2 = np.array([2.0, -3.0, 0.2]), np.array([12.0, 4.0, 0.7])
    m1, m2 = render(world, pw, p1, grid), render(world, pw, p2, grid)
    true = relative_pose(p1, p2)[None]
    noisy = true + np.array([[2.0, -1.0, np.radians(9.0)]])
    label = dempster(m1, warp_masses(m2, true[0], grid))[None]
    x = FusionInput(
        map1=m1[None],
        map2=m2[None],
        rel_pose_noisy=noisy,
        rel_pose_true=true,
        grid=grid,
        registration=RegistrationParams(),
    )
    frame, _ = evaluate_method(
        "registered", x, label, EvalSettings(success_trans_m=0.5, success_rot_deg=1.0)
    )
    row = frame.iloc[0]
    assert row["reg_accepted"] and row["reg_success"]
    assert row["reg_trans_err_m"] < 0.25 < row["noisy_trans_err_m"]
    naive = dempster(m1, warp_masses(m2, noisy[0], grid))[None]
    assert row["kld_fo"] < 0.2 * kld_fo(label, naive)[0]


def test_registry_lists_every_method_once_with_its_inputs():
    from traffictwin.fusion.methods import INPUTS, register

    assert list(REGISTRY) == [
        "ego",
        "naive",
        "naive-yager",
        "naive-cautious",
        "registered",
        "dnn",
        "registered+network",
        "learned",
        "learned+network",
        "learned-refined",
        "learned-refined+network",
    ]
    for name, m in REGISTRY.items():
        assert m.name == name and m.description and m.label and set(m.needs) <= set(INPUTS)
    assert REGISTRY["registered"].needs == ("raw",) and REGISTRY["registered"].slow
    assert "model" in REGISTRY["dnn"].needs
    assert REGISTRY["learned"].needs == ("prealigned", "pose", "model")
    assert not REGISTRY["learned"].slow  # evaluated on every pair
    assert REGISTRY["learned-refined"].needs == ("prealigned", "raw", "model")
    assert not REGISTRY["learned-refined"].slow  # on the same pairs as `learned`
    with pytest.raises(ValueError, match="registered twice"):
        register("naive", "again", needs=("prealigned",))(lambda x: x.inputs[:, :2])
    with pytest.raises(ValueError, match="unknown needs"):
        register("x", "y", needs=("lidar",))


def test_a_new_method_is_one_function_and_one_registration():
    from traffictwin.fusion import methods

    @methods.register("half", "map 1 with half the masses", needs=("prealigned",))
    def _half(x):
        return 0.5 * x.inputs[:, :2]

    try:
        rng = np.random.default_rng(5)
        m1, m2 = random_masses(rng, 3), random_masses(rng, 3)
        x = FusionInput(inputs=np.concatenate([m1, m2], axis=1))
        np.testing.assert_allclose(methods.fuse("half", x).masses, 0.5 * m1)
        frame, _ = evaluate_method(
            "half", x, m1, EvalSettings(batch_size=2, success_trans_m=0.5, success_rot_deg=1.0)
        )
        assert len(frame) == 3 and list(methods.METHODS)[-1] == "half"
    finally:
        methods.METHODS.pop("half")


def test_evaluate_method_subsets_and_registered_diagnostics():
    from traffictwin.fusion.evaluation import evenly_spaced

    np.testing.assert_array_equal(evenly_spaced(10, None), np.arange(10))
    np.testing.assert_array_equal(evenly_spaced(10, 3), [0, 4, 9])  # spread, first and last
    np.testing.assert_array_equal(evenly_spaced(3, 5), [0, 1, 2])
    rng = np.random.default_rng(6)
    m1, m2 = random_masses(rng, 4), random_masses(rng, 4)
    x = FusionInput(inputs=np.concatenate([m1, m2], axis=1))
    sub = x.take(np.array([1, 3]))
    assert len(sub) == 2 and sub.map1 is None
    np.testing.assert_array_equal(sub.inputs[:, :2], m1[[1, 3]])
    with pytest.raises(ValueError, match="prediction shape"):
        evaluate_method(
            "ego", x, m1[:, :, :8], EvalSettings(success_trans_m=0.5, success_rot_deg=1.0)
        )


def test_eval_config_is_typed_and_the_configurations_come_from_configurations():
    from omegaconf import OmegaConf

    from traffictwin.config import ConfigError
    from traffictwin.fusion.config import fusion_eval_config, pose_configurations

    root = Path(__file__).resolve().parents[1]
    cfg = OmegaConf.create(yaml.safe_load((root / "params.yaml").read_text()))
    fc = fusion_eval_config(cfg)
    assert fc.registration_params.feature == cfg.evaluation.fusion.registration.feature
    assert fc.refinement_params.ecc_levels == cfg.evaluation.fusion.refinement.ecc_levels
    assert list(pose_configurations(cfg)) == list(cfg.configurations)  # conf order
    for key, value, match in (
        ("configs", ["A"], "evaluation.fusion.configs"),  # removed: derived from configurations
        ("max_pairs", 0, "evaluation.fusion.max_pairs' must be >= 1"),
        ("split", "dev", "evaluation.fusion.split"),
        ("registration", {"feature": "edges"}, "evaluation.fusion.registration"),
        ("refinement", {"ecc_levels": 0}, "evaluation.fusion.refinement"),
        ("validation.split", "test", "must differ from the evaluated split"),
        ("validation.refinement_grid", {"ecc_levels": []}, "non-empty list"),
        ("trans_bins_m", [0, -1], r"evaluation.fusion.trans_bins_m\[1\]"),
    ):
        bad = OmegaConf.create(OmegaConf.to_container(cfg))
        OmegaConf.update(bad, f"evaluation.fusion.{key}", value, merge=False)
        with pytest.raises(ConfigError, match=match):
            fusion_eval_config(bad)
    bad = OmegaConf.create(OmegaConf.to_container(cfg))
    OmegaConf.update(bad, "configurations.B.alpha", -1.0, merge=False)
    with pytest.raises(ConfigError, match="configurations.B.alpha"):
        pose_configurations(bad)


def test_json_clean_and_mlflow_numbers():
    from traffictwin.fusion.evaluation import methods_table, mlflow_metrics
    from traffictwin.io.jsonio import json_clean

    m = json_clean(
        {
            "test": {
                "A": {
                    "dnn": {"k": np.float32(0.5), "k_ci": {"lo": 0.4, "hi": np.float64(0.6)}},
                    "naive": {"k": float("nan"), "n": 3},
                    "dnn[paper]": {"k": 0.7},
                    "dnn[per-config]": {"k": 0.3},
                }
            },
            "cross": {"dnn[per-config]-A": {"A": {"k": 0.25}, "B": {"k": np.inf}}},
            "ids": (np.int64(1), 2.0),
        }
    )
    assert m["test"]["A"]["naive"]["k"] is None
    assert m["cross"]["dnn[per-config]-A"]["B"]["k"] is None
    assert m["ids"] == [1, 2.0] and isinstance(m["ids"][0], int)
    # a network's run gets its own numbers only; the other rows go to the methods table
    assert mlflow_metrics(m, "A") == {"test/k": 0.5, "test/k_ci_lo": 0.4, "test/k_ci_hi": 0.6}
    # a variant's own run: its row is test/, no cross table
    assert mlflow_metrics(m, "A", "dnn[paper]") == {"test/k": 0.7}
    # a second row in the same run under its own prefix, made MLflow-safe (no "+", "[" or "]")
    assert mlflow_metrics(m, "A", "dnn[paper]", "test/A/registered+network/") == {
        "test/A/registered_network/k": 0.7
    }
    # a per-configuration network's run: its row and its cross table (on the other configurations)
    assert mlflow_metrics(m, "A", "dnn[per-config]") == {"test/k": 0.3, "cross_A/k": 0.25}
    table = methods_table(m, "A")
    assert list(table.columns) == ["method", "k", "k_ci_hi", "k_ci_lo", "n"]
    assert table["method"].tolist() == ["dnn", "naive", "dnn[paper]", "dnn[per-config]"]
    assert table.loc[0, "k_ci_lo"] == 0.4 and table.loc[2, "k"] == 0.7
    assert table.loc[1, "n"] == 3 and pd.isna(table.loc[1, "k"]) and pd.isna(table.loc[2, "n"])


def _ci(v: float, half: float) -> dict:
    return {"lo": v - half, "hi": v + half}


def _metrics(net: dict[str, float], naive: dict[str, float], half: float = 0.01) -> dict:
    """fusion.json-like metrics: KLD(b) of the network / naive per configuration, intervals of
    half-width ``half`` around each estimate and around each network − naive difference."""
    test, diff = {}, {}
    for c in CFGS:
        base = {"kld_fou_q25": 0.1, "kld_fou_q75": 0.3, "dice_occ": 0.8, "u_mean": 0.3}
        reg = (net[c] + naive[c]) / 2
        test[c] = {
            "naive": {**base, "kld_fou_mean": naive[c], "kld_fou_q75": 0.1 + 2 * naive[c]},
            "dnn": {
                **base,
                "kld_fou_mean": net[c],
                "kld_fo_mean": net[c] / 2,
                "dice_occ": 0.9 if net[c] < naive[c] else 0.5,
                "u_auroc": 0.8,
                "u_auroc_ci": _ci(0.8, 0.05),
            },
            "registered": {
                **base,
                "kld_fou_mean": reg,
                "success_rate": 0.5,
                "residual_trans_m_median": 0.2,
                "noisy_trans_m_median": 1.0,
            },
        }
        for row in test[c].values():
            row.update({f"{k}_ci": _ci(row[k], half) for k in ("kld_fou_mean", "dice_occ")})
        d = net[c] - naive[c]
        dd = test[c]["dnn"]["dice_occ"] - 0.8
        diff[c] = {
            "dnn": {
                "vs_naive": {
                    "kld_fou_mean": {"estimate": d, **_ci(d, half)},
                    "kld_fo_mean": {"estimate": d / 2, **_ci(d / 2, half)},
                    "dice_occ": {"estimate": dd, **_ci(dd, half)},
                },
                "vs_registered": {
                    "kld_fou_mean": {"estimate": net[c] - reg, **_ci(net[c] - reg, half)}
                },
            },
            "registered": {
                "vs_naive": {
                    "kld_fou_mean": {"estimate": reg - naive[c], **_ci(reg - naive[c], half)}
                }
            },
        }
    return {
        "test": test,
        "diff": diff,
        "label": {c: {"u_mean": 0.5} for c in CFGS},
        "bootstrap": {"n_boot": 2000, "level": 0.95, "cluster": "scenario = pair_id // 1000"},
        "cross": {
            f"dnn-{c}": {t: {"kld_fou_mean": 0.1 if c == t else 0.2} for t in CFGS} for c in CFGS
        },
    }


def test_findings_claim_only_differences_whose_interval_excludes_zero():
    paper_like = fusion_findings(
        _metrics(
            {"A": 0.2, "B": 0.2, "C": 0.25, "D": 0.3}, {"A": 0.0, "B": 0.4, "C": 0.6, "D": 0.8}
        )
    )
    assert (
        "lower in 3/3 configurations (B, C, D)" in paper_like
        and "this reproduces" in paper_like.lower()
    )
    assert "network lower at B, C, D" in paper_like
    assert "D -0.500 [-0.510, -0.490]" in paper_like  # the difference with its interval
    # configuration A against naive: the verdict table's claim, not the findings
    assert "**Configuration A" not in paper_like
    assert "A 0.800 [0.750, 0.850]" in paper_like and "above 0.5) in 4/4" in paper_like
    assert "Cross table" not in paper_like  # the report's cross table shows it
    # the classical registration: the estimate, paired-difference and registration tables
    assert "**Classical registration" not in paper_like
    # the same estimates with wide intervals: nothing is claimed
    noisy = fusion_findings(
        _metrics(
            {"A": 0.2, "B": 0.2, "C": 0.25, "D": 0.3},
            {"A": 0.0, "B": 0.4, "C": 0.6, "D": 0.8},
            half=1.0,
        )
    )
    assert "lower in 0/3 configurations (none)" in noisy and "does not reproduce" in noisy
    assert "no difference shown at B, C, D" in noisy
    opposite = fusion_findings(_metrics({c: 1.0 for c in CFGS}, {c: 0.1 for c in CFGS}))
    assert "network higher at B, C, D" in opposite
    assert fusion_findings({}).startswith("## Fusion findings")


def test_findings_explain_negative_kld_a_variants_and_targets():
    m = _metrics({c: 1.5 for c in CFGS}, {"A": 0.0, "B": 0.2, "C": 0.25, "D": 0.3})
    for c in CFGS:
        m["test"][c]["dnn"]["kld_fo_mean"] = -0.03
    text = fusion_findings(m)
    assert "Negative KLD(a) (A, B, C, D)" in text and "KLD(b) is the headline" in text
    assert "Mean u, network vs label:** A 0.300 vs 0.500" in text
    m["test"]["D"]["dnn[paper]"] = {"kld_fou_mean": 0.9, "kld_fou_mean_ci": _ci(0.9, 0.1)}
    m["diff"]["D"]["dnn[paper]"] = {
        "vs_naive": {"kld_fou_mean": {"estimate": 0.6, "lo": 0.5, "hi": 0.7}}
    }
    m["targets"] = {
        "u_auroc": {"status": "fail"},
        "dice_occ_at_A": {"status": "pass"},
        "x": {"status": "not evaluated"},
    }
    text = fusion_findings(m)
    # the other network rows and the targets: the report's tables, not the findings
    assert "Row `dnn[paper]`" not in text and "**Targets" not in text
    # the stage writes fusion.json with sorted keys: the findings must not depend on key order
    assert fusion_findings(json.loads(json.dumps(m, sort_keys=True))) == text
    assert "Negative KLD(a)" not in fusion_findings(
        _metrics({c: 0.1 for c in CFGS}, {c: 0.2 for c in CFGS})
    )


def test_kld_boxplot_plots_one_box_per_config_and_method(tmp_path):
    from traffictwin.fusion.figures import kld_boxplot
    from traffictwin.io.atomic import save_figure

    rng = np.random.default_rng(2)
    vals = {
        m: {c: rng.gamma(2.0, 0.1 * (i + 1), 20) for i, c in enumerate(CFGS)}
        for m in ("naive", "dnn")
    }
    vals["naive"]["D"] = np.array([np.nan])  # no finite value: no box
    fig = kld_boxplot(vals, CFGS, ["naive", "dnn"])
    ax = fig.axes[0]
    boxes = {p.get_gid(): p for p in ax.patches if p.get_gid()}
    medians = {line.get_gid(): line for line in ax.lines if line.get_gid()}
    assert sorted(boxes) == sorted(
        f"{m}/{c}" for m in ("naive", "dnn") for c in CFGS if (m, c) != ("naive", "D")
    )
    # each box spans the quartiles of its configuration x method values
    for gid, box in boxes.items():
        m, c = gid.split("/")
        y = box.get_path().vertices[:, 1]
        q25, q75 = np.quantile(vals[m][c], [0.25, 0.75])
        assert y.min() == pytest.approx(q25) and y.max() == pytest.approx(q75), gid
        np.testing.assert_allclose(medians[f"{gid}/median"].get_ydata(), np.median(vals[m][c]))
    # the quantity, its unit and the (symmetric) log scale: KLD >= 0, rows decades apart
    assert ax.get_ylabel().startswith("KLD(label ‖ prediction)\n(nats per cell; log scale")
    assert ax.get_yscale() == "symlog" and ax.get_ylim()[0] == 0
    assert [t.get_text() for t in ax.get_xticklabels()] == list(CFGS)
    assert ax.get_xlabel() == "configuration"
    assert [t.get_text() for t in ax.get_legend().get_texts()] == [
        REGISTRY["naive"].label,
        REGISTRY["dnn"].label,
    ]
    png_ok(save_figure(fig, tmp_path / "box.png"))


def test_configuration_axes_carry_the_pose_noise() -> None:
    """With the configurations' (r m, α deg), every configuration axis says what they are."""
    from traffictwin.fusion.figures import (
        CONFIG_AXIS,
        CONFIG_NOTE,
        config_label,
        kld_boxplot,
        score_figure,
    )
    from traffictwin.report.plot_data import fusion_scores_long

    noise = {"A": (0.0, 0.0), "D": (5.0, 20.0)}
    assert config_label("D", noise) == "D\nr 5 m\nα 20°"
    assert config_label("B", noise) == "B" and config_label("D") == "D"
    want = ["A\nr 0 m\nα 0°", "D\nr 5 m\nα 20°"]
    box = kld_boxplot({"dnn": {c: [0.1, 0.2] for c in noise}}, list(noise), ["dnn"], noise=noise)
    wide = pd.DataFrame(
        {"config": list(noise), "noise_r_m": [0.0, 5.0], "noise_alpha_deg": [0.0, 20.0]}
        | {"dnn_dice_occ": [0.9, 0.8]}
    )
    occ = score_figure(fusion_scores_long(wide), noise, "occupied")
    for ax in (box.axes[0], *occ.axes):
        assert [t.get_text() for t in ax.get_xticklabels()] == want
        assert ax.get_xlabel().startswith(CONFIG_AXIS)
    # what r and α mean, in plain words: once per figure (axis label / title)
    assert box.axes[0].get_xlabel() == f"{CONFIG_AXIS}\n{CONFIG_NOTE}"
    assert CONFIG_NOTE in occ.get_suptitle() and "98 %" in CONFIG_NOTE
    assert "noisy poses" in CONFIG_NOTE and "r (m)" in CONFIG_NOTE and "α (°)" in CONFIG_NOTE


def test_qualitative_grid_shows_each_map(tmp_path):
    from traffictwin.fusion.map_figures import qualitative_grid
    from traffictwin.io.atomic import save_figure
    from traffictwin.report.colours import LEGEND, map_extent, masses_to_rgb

    rng = np.random.default_rng(2)
    maps = random_masses(rng, 4, 64, 48)
    rows = {"label": list(maps), "naive": list(maps[::-1])}
    fig = qualitative_grid(rows, CFGS, cell=0.5)
    axes = np.array(fig.axes).reshape(2, len(CFGS))
    for r, name in enumerate(rows):
        assert axes[r][0].get_ylabel() == f"{name}\nx (m, forward)"
        for c, cfg in enumerate(CFGS):
            img = axes[r][c].get_images()[0]
            # the shared colour map, in metres: 48 cols x 0.5 m wide, 64 rows x 0.5 m long
            np.testing.assert_allclose(img.get_array(), masses_to_rgb(rows[name][c]))
            assert img.get_extent() == list(map_extent(64, 48, 0.5)) == [12.0, -12.0, -16.0, 16.0]
            if r == 0:
                assert axes[r][c].get_title() == f"config {cfg}"
    assert axes[-1][0].get_xlabel() == "y (m, + = left)"
    (legend,) = fig.legends
    assert [t.get_text() for t in legend.get_texts()] == [label for label, _ in LEGEND]
    png_ok(save_figure(fig, tmp_path / "q.png"))


# -- stage on the ci DAG (slow) ---------------------------------------------------------------------
def _declared_outputs(repo: Path) -> list[Path]:
    stage = yaml.safe_load((repo / "dvc.yaml").read_text())["stages"]["evaluate_fusion"]
    paths = []
    for key in ("outs", "metrics", "plots"):
        for item in stage.get(key, []):
            paths.append(repo / (next(iter(item)) if isinstance(item, dict) else item))
    return paths


@pytest.mark.slow
def test_stage_writes_every_declared_output(ci_dag: Path):
    outs = _declared_outputs(ci_dag)
    assert len(outs) >= 8
    for p in outs:
        assert p.exists() and p.stat().st_size > 0, p
        if p.suffix == ".png":
            png_ok(p)
    # no figure of its own (plot_data draws them): the maps of Fig. 4 and the figures' metadata
    assert not [p for p in outs if p.suffix == ".png"]
    assert ci_dag / "data" / "figure_inputs" / "fusion.npz" in outs


@pytest.mark.slow
def test_stage_metrics_layout_and_values(ci_dag: Path):
    m = json.loads((ci_dag / "reports" / "metrics" / "fusion.json").read_text())
    assert sorted(m["test"]) == list(CFGS)
    for c in CFGS:
        for meth in METHODS:
            v = m["test"][c][meth]
            for k in (
                "kld_fo_mean",
                "kld_fou_mean",
                "dice_occ",
                "precision_free",
                "recall_free",
                "u_mean",
            ):
                assert v[k] is not None and math.isfinite(v[k]), (c, meth, k)
            assert "ms_per_pair" not in v  # wall time: in the run record only
            assert run_record(ci_dag, "evaluate_fusion")["ms_per_pair"][c][meth] > 0
            assert v["kld_fou_mean"] >= -1e-6 and 0 <= v["dice_occ"] <= 1
            for k in CI_KEYS:  # the interval of every headline metric (null where undefined)
                ci = v[f"{k}_ci"]
                assert set(ci) == {"lo", "hi"}
                if ci["lo"] is not None and v[k] is not None:
                    assert ci["lo"] - 1e-9 <= v[k] <= ci["hi"] + 1e-9, (c, meth, k)
            if meth != "naive":
                d = m["diff"][c][meth]["vs_naive"]
                assert set(d) == set(DIFF_KEYS) and d["kld_fou_mean"]["n_pairs"] >= 1
        assert 0 <= m["test"][c]["registered"]["success_rate"] <= 1
        assert 0 <= m["label"][c]["u_mean"] <= 1
        assert m["test"][c]["dnn"]["u_auroc"] is None or 0 <= m["test"][c]["dnn"]["u_auroc"] <= 1
    # zero noise: the naive fusion is the label's construction
    assert (
        m["test"]["A"]["naive"]["kld_fo_mean"] < 1e-6 and m["test"]["A"]["naive"]["dice_occ"] == 1.0
    )
    # one model per task: no per-configuration networks, so no cross table on the default DAG
    assert m["cross"] == {}
    # the one network and its hybrids at every configuration
    assert all(
        {"dnn", "registered+network", "learned", "learned+network"} <= set(m["test"][c])
        for c in CFGS
    )
    assert set(m["bins"]) == {"translation", "rotation"} and "naive" in m["bins"]["translation"]
    # targets judged on wall times are in the stage's run record, not in fusion.json
    assert set(m["targets"]) == set(JUDGES) - set(TIMING_TARGETS)
    for t in m["targets"].values():
        assert t["status"] in ("pass", "fail", "not evaluated")
    # the training target reads the one network's training record (judged, never left unjudged)
    trained = json.loads((ci_dag / "reports/metrics/train_fusion_network.json").read_text())
    conv = m["targets"]["training_converged"]["per_config"]["mixed"]
    assert (conv["best_epoch"], conv["epochs"]) == (trained["best_epoch"], trained["epochs"])
    assert conv["stopped_early"] is trained["stopped_early"] and conv["status"] != "not evaluated"
    rec = run_record(ci_dag, "evaluate_fusion")
    assert set(rec["targets"]) == set(TIMING_TARGETS) and "runtime_ms_per_pair" not in m
    assert rec["runtime_ms_per_pair"]["naive"] > 0
    assert m["bootstrap"]["n_boot"] >= 100
    samples = pd.read_csv(ci_dag / "reports" / "fusion_eval_samples.csv")
    assert "ms" not in samples
    n = m["n_pairs"]["per_config"]
    assert (samples[samples.method == "naive"].groupby("config").size() == n).all()
    assert (
        samples[samples.method == "registered"].groupby("config").size()
        == m["n_pairs"]["registered"]
    ).all()
    # the same pairs and noise draws for every method of a configuration
    for c in CFGS:
        s = samples[samples.config == c]
        ids = {
            meth: sorted(g.pair_id)
            for meth, g in s.groupby("method")
            if not meth.startswith("dnn[per-config]-")
        }
        assert ids["naive"] == ids["dnn"] == ids["ego"]
    findings = (ci_dag / "reports" / "fusion_findings.md").read_text()
    assert findings == fusion_findings(m)


@pytest.mark.slow
def test_naive_at_configuration_A_equals_the_label_exactly(ci_dag: Path):
    from traffictwin.io.shards import Dataset

    d = Dataset(ci_dag / "data" / "prealigned" / "A", kind="prealigned").load_all("test")
    assert np.all(d["noise"] == 0)
    np.testing.assert_allclose(fuse_prealigned(d["inputs"], "naive"), d["label"], atol=1e-6)


@pytest.mark.slow
def test_numbers_logged_to_each_networks_mlflow_run(ci_dag: Path):
    from mlflow.tracking import MlflowClient

    m = json.loads((ci_dag / "reports" / "metrics" / "fusion.json").read_text())
    client = MlflowClient(tracking_uri=f"sqlite:///{ci_dag / 'mlflow.db'}")
    # the one network's run holds its numbers at every configuration, test/<cfg>/<metric>
    run_id = run_record(ci_dag, "train_fusion")["run_id"]
    logged = client.get_run(run_id).data.metrics
    for c in CFGS:
        dnn = m["test"][c]["dnn"]
        assert logged[f"test/{c}/kld_fou_mean"] == pytest.approx(dnn["kld_fou_mean"])
        assert logged[f"test/{c}/kld_fou_mean_ci_lo"] == pytest.approx(dnn["kld_fou_mean_ci"]["lo"])
        assert logged[f"test/{c}/kld_fo_mean"] == pytest.approx(dnn["kld_fo_mean"])
        # the same network on registered pairs: its own keys in the same run
        hyb = m["test"][c]["registered+network"]
        assert logged[f"test/{c}/registered_network/kld_fou_mean"] == pytest.approx(
            hyb["kld_fou_mean"]
        )
        table = json.loads(
            Path(client.download_artifacts(run_id, f"evaluation/test_methods_{c}.json")).read_text()
        )
        rows = {r[0]: dict(zip(table["columns"], r)) for r in table["data"]}
        assert rows["naive"]["dice_occ"] == pytest.approx(m["test"][c]["naive"]["dice_occ"])
    assert not any(k.startswith("test_") for k in logged)  # baselines: the table artifacts


def test_every_method_has_its_own_style() -> None:
    """Each registered fusion method (and network variant row) is drawn in a colour + marker no
    other method uses, so no two lines of a figure look alike."""
    from traffictwin.fusion.figures import METHOD_STYLE
    from traffictwin.fusion.methods import METHODS

    assert set(METHODS) <= set(METHOD_STYLE), sorted(set(METHODS) - set(METHOD_STYLE))
    looks = [(st["color"].lower(), st["marker"]) for st in METHOD_STYLE.values()]
    assert len(set(looks)) == len(looks)
    assert len({c for c, _ in looks}) == len(looks)  # colours alone tell them apart too


def test_findings_give_the_cells_behind_auroc_and_say_too_few_instead():
    m = _metrics({"A": 0.01, "B": 0.2, "C": 0.25, "D": 0.3}, {c: 0.5 for c in CFGS})
    counts = {"u_auroc_n_wrong": 1234, "u_auroc_n_right": 567890, "u_auroc_pairs_wrong": 150}
    for c in ("B", "C", "D"):
        m["test"][c]["dnn"].update(counts, u_auroc_enough=True)
    m["test"]["A"]["dnn"].update(
        u_auroc=float("nan"),
        u_auroc_ci=_ci(float("nan"), 0.0),
        u_auroc_enough=False,
        u_auroc_n_wrong=37,
        u_auroc_n_right=600000,
        u_auroc_pairs_wrong=4,
    )
    # learned registration refined by ECC: the report's registration table shows it, not the findings
    for c in CFGS:
        m["test"][c]["learned-refined"] = {
            "success_rate": 0.96,
            "success_rate_ci": _ci(0.96, 0.02),
            "fallback_rate": 0.1,
            "residual_trans_m_p90": 0.3,
            "residual_rot_deg_p90": 0.4,
        }
        m["diff"][c]["learned-refined"] = {
            "vs_registered": {"success_rate": {"estimate": 0.14, **_ci(0.14, 0.04)}}
        }
    text = fusion_findings(m)
    assert "B 0.800 [0.750, 0.850] (1,234 wrong cells in 150 pairs, 567,890 right)" in text
    assert "above 0.5) in 3/3 configurations" in text
    assert "Too few wrong cells" in text and "A (37 wrong cells in 4 pairs, 600,000 right)" in text
    assert "A nan" not in text and "A 0.800" not in text
    assert "Learned registration" not in text  # the report's registration table shows it
