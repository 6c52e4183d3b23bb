"""reports/summary.json (the headline numbers, the only DVC metrics file), the report's page layout
(headline first, appendix collapsed), the zoomed fusion score figures and the shared mass
colour map. Synthetic inputs with hand-computed expectations."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from _report_pages import all_html, page_md

from pipelines.report import providers
from traffictwin.fusion import figures as SF
from traffictwin.fusion import report_section as F
from traffictwin.report import colours as C
from traffictwin.report import render as R
from traffictwin.report.model import ReportInputs
from traffictwin.report.summary import (
    Baseline,
    Headline,
    headline,
    interval,
    strongest,
    summary_json,
)
from traffictwin.risk import report_section as RS
from traffictwin.twin import report_section as TS

CONFS = {"A": (0.0, 0.0), "D": (5.0, 20.0)}


def _ci(lo: float, hi: float) -> dict[str, float]:
    return {"lo": lo, "hi": hi}


FUSION = {
    "test": {
        "A": {
            "dnn": {
                "kld_fou_mean": 0.01,
                "kld_fou_mean_ci": _ci(0.008, 0.012),
                "dice_occ": 0.99,
                "dice_occ_ci": _ci(0.985, 0.995),
            }
        },
        # D: Dice without an interval -> left out; KLD present
        "D": {"dnn": {"kld_fou_mean": 0.06, "kld_fou_mean_ci": _ci(0.05, 0.07), "dice_occ": 0.9}},
    }
}
RISK = {
    "main_variant": "headline",
    "thresholds_s": [1.5, 1.0],
    "groups": {
        "headline": {
            "at_1.5s": {
                "roc_auc": 0.84,
                "roc_auc_ci": _ci(0.79, 0.88),
                "balanced_accuracy": 0.8,
                "balanced_accuracy_ci": _ci(0.75, 0.85),
            },
            "test/mse": 0.005,
            "test/mse_ci": _ci(0.001, 0.01),
        }
    },
    "models": {"headline": {"test/mse": 0.9, "test/mse_ci": _ci(0.8, 1.0)}},  # the group wins
}
TWIN = {
    "headline": "learned",
    "targets": {"configuration": "D", "method": "learned"},
    "configurations": {
        "D": {
            "methods": {
                "learned": {
                    "occluded": {
                        "recall": 0.99,
                        "recall_ci": [0.98, 1.0],
                        "recall_vs_ego": 0.1,
                        "recall_vs_ego_ci": [0.06, 0.15],
                    }
                }
            }
        }
    },
}


# --------------------------------------------------------------------------- summary.json
def test_headline_needs_a_value_and_an_interval() -> None:
    assert headline("k", "q", "w", 0.5, [0.4, 0.6]) == [Headline("k", "q", "w", 0.5, 0.4, 0.6)]
    assert headline("k", "q", "w", 0.5, None) == []
    assert headline("k", "q", "w", float("nan"), [0.4, 0.6]) == []
    assert headline("k", "q", "w", None, [0.4, 0.6]) == []
    assert headline("k", "q", "w", True, [0.4, 0.6]) == []  # a flag is not a number
    assert interval({"lo": 1, "hi": 2}) == (1.0, 2.0) and interval([1, None]) is None


def test_summary_json_nests_dotted_keys_with_their_interval() -> None:
    h = {
        "fusion": [Headline("A.kld", "q", "w", 0.1, 0.05, 0.2)],
        "risk": [Headline("auc", "q", "w", 0.8, 0.7, 0.9)],
        "twin": [],
    }
    assert summary_json(h) == {
        "fusion": {"A": {"kld": 0.1, "kld_lo": 0.05, "kld_hi": 0.2}},
        "risk": {"auc": 0.8, "auc_lo": 0.7, "auc_hi": 0.9},
    }


def test_problem_headlines_from_their_metrics_files() -> None:
    fusion = F.headlines({"fusion.json": FUSION}, CONFS)
    assert [(h.key, h.value, h.lo, h.hi) for h in fusion] == [
        ("A.kld", 0.01, 0.008, 0.012),
        ("A.dice", 0.99, 0.985, 0.995),
        ("D.kld", 0.06, 0.05, 0.07),
    ]
    assert "r = 5 m, α = 20°" in fusion[-1].where
    risk = RS.headlines({"risk.json": RISK})
    assert [(h.key, h.value, h.lo, h.hi) for h in risk] == [
        ("auc", 0.84, 0.79, 0.88),
        ("balanced_accuracy", 0.8, 0.75, 0.85),
    ]
    # the shipped predictor (chosen on validation) is the headline when there is one
    shipped = {
        **RISK,
        "shipped": "shipped",
        "models": {
            **RISK["models"],
            "shipped": {"at_1.5s": {"roc_auc": 0.9, "roc_auc_ci": _ci(0.85, 0.95)}},
        },
    }
    [h] = RS.headlines({"risk.json": shipped})
    assert (h.key, h.value) == ("auc", 0.9) and "shipped predictor" in h.where
    assert "THW < 1.5 s" in risk[0].quantity
    twin = TS.headlines({"twin.json": TWIN})
    assert [(h.key, h.value, h.lo, h.hi) for h in twin] == [
        ("recall", 0.99, 0.98, 1.0),
        ("recall_gain", 0.1, 0.06, 0.15),
    ]
    # nothing evaluated yet: no numbers, no error
    assert F.headlines({}, CONFS) == [] and RS.headlines({}) == [] and TS.headlines({}) == []


def test_strongest_baseline_beside_each_headline() -> None:
    """The best baseline on the same quantity and frames: fusion rules without a network (lower
    KLD, higher Dice), risk baselines but the oracle and the rule on exact disparity, the twin's
    other maps; its value sourced from its metrics file, its interval beside it."""
    assert strongest({}, higher_better=True) is None
    got = strongest(
        {"a": (0.5, None, "f#a"), "b": (0.7, [0.6, 0.8], "f#b"), "c": (None, None, "f#c")},
        higher_better=True,
    )
    assert got == Baseline("b", 0.7, 0.6, 0.8, "f#b")
    assert strongest({"a": (0.5, None, "f#a"), "b": (0.7, None, "f#b")}, higher_better=False) == (
        Baseline("a", 0.5, None, None, "f#a")
    )
    a = FUSION["test"]["A"]
    fusion = {
        "test": {
            "A": {
                **a,
                "naive": {"kld_fou_mean": 0.0, "kld_fou_mean_ci": _ci(0.0, 0.0), "dice_occ": 0.97},
                "registered": {"kld_fou_mean": 0.002, "dice_occ": 0.98},
                "learned": {"kld_fou_mean": -1.0, "dice_occ": 1.0},  # learned: no baseline
            }
        }
    }
    kld, dice = F.headlines({"fusion.json": fusion}, {"A": (0.0, 0.0)})
    assert kld.baseline == Baseline(
        "naive (noisy pose + Dempster)",
        0.0,
        0.0,
        0.0,
        "metrics/fusion.json#test.A.naive.kld_fou_mean",
    )
    assert dice.baseline is not None and dice.baseline.name == "registered (FM + ECC) + Dempster"
    assert (dice.baseline.value, dice.baseline.lo) == (0.98, None)
    at = {"roc_auc": 0.7, "roc_auc_ci": _ci(0.6, 0.8)}
    risk = {
        **RISK,
        "baselines": {
            "geometric_gt": {"uses_gt_disparity": True, "at_1.5s": {"roc_auc": 0.99}},
            "oracle": {"oracle": True, "at_1.5s": {"roc_auc": 1.0}},
            "speed_only": {"at_1.5s": at},
            "train_mean": {"at_1.5s": {"roc_auc": 0.5}},
        },
    }
    auc, bacc = RS.headlines({"risk.json": risk})
    assert auc.baseline == Baseline(
        "speed_only", 0.7, 0.6, 0.8, "metrics/risk.json#baselines.speed_only.at_1.5s.roc_auc"
    )
    assert bacc.baseline is None  # no baseline has the number
    methods = TWIN["configurations"]["D"]["methods"]
    twin = {
        **TWIN,
        "configurations": {
            "D": {
                "methods": {
                    **methods,
                    "ego": {"occluded": {"recall": 0.8, "recall_ci": [0.7, 0.9]}},
                    "naive": {"occluded": {"recall": 0.9, "recall_ci": [0.85, 0.95]}},
                }
            }
        },
    }
    recall, gain = TS.headlines({"twin.json": twin})
    assert recall.baseline is not None and recall.baseline.value == 0.9
    assert recall.baseline.src == "metrics/twin.json#configurations.D.methods.naive.occluded.recall"
    assert gain.baseline is None
    # summary.json stays the headline numbers only
    assert summary_json({"risk": [auc]}) == {"risk": {"auc": 0.84, "auc_lo": 0.79, "auc_hi": 0.88}}


@pytest.fixture
def reports(tmp_path: Path) -> Path:
    rep = tmp_path / "reports"
    (rep / "metrics").mkdir(parents=True)
    for name, data in {"fusion.json": FUSION, "risk.json": RISK, "twin.json": TWIN}.items():
        (rep / "metrics" / name).write_text(json.dumps(data))
    (rep / "metrics" / "extra.json").write_text(json.dumps({"x": 1.5}))
    return rep


def test_write_report_writes_the_summary_and_shows_it_first(reports: Path) -> None:
    inputs = ReportInputs(reports_dir=reports, profile="ci", seed=1, git_commit="c0ffee")
    rep = R.write_report(inputs, providers(CONFS))
    summary = json.loads((reports / "summary.json").read_text())
    assert summary == {
        "fusion": {
            "A": {
                "kld": 0.01,
                "kld_lo": 0.008,
                "kld_hi": 0.012,
                "dice": 0.99,
                "dice_lo": 0.985,
                "dice_hi": 0.995,
            },
            "D": {"kld": 0.06, "kld_lo": 0.05, "kld_hi": 0.07},
        },
        "risk": {
            "auc": 0.84,
            "auc_lo": 0.79,
            "auc_hi": 0.88,
            "balanced_accuracy": 0.8,
            "balanced_accuracy_lo": 0.75,
            "balanced_accuracy_hi": 0.85,
        },
        "twin": {
            "recall": 0.99,
            "recall_lo": 0.98,
            "recall_hi": 1.0,
            "recall_gain": 0.1,
            "recall_gain_lo": 0.06,
            "recall_gain_hi": 0.15,
        },
    }

    # every leaf is a number inside its interval (what `dvc metrics show` lists)
    def leaves(d: dict, p: str = "") -> dict[str, float]:
        out = {}
        for k, v in d.items():
            out.update(leaves(v, f"{p}{k}.") if isinstance(v, dict) else {f"{p}{k}": v})
        return out

    flat = leaves(summary)
    for k, v in flat.items():
        if not k.endswith(("_lo", "_hi")):
            assert flat[f"{k}_lo"] <= v <= flat[f"{k}_hi"], k
    assert len(flat) <= 45
    # the index: the papers' verdicts, then headline results, its numbers sourced from summary.json
    assert [s.title for s in rep.sections[:2]] == [R.VERDICTS_TITLE, "Headline results"]
    assert rep.sections[0].page == rep.sections[1].page == ""  # both on the index
    page = all_html(reports)  # the index, then every page in reading order
    md = (reports / "README.md").read_text()
    order = ["<strong>Paper claims against this run</strong>", "<strong>Headline results ("]
    order += [f'<h2 id="{R._slug(F.TITLE)}">', '<h2 id="appendix--every-metrics-file">']
    assert [page.index(x) for x in order] == sorted(page.index(x) for x in order)
    cells = [c for s in rep.sections for t in s.tables for r in t.rows for c in r]
    assert any(c.src == "summary.json#risk.auc" and c.value == 0.84 for c in cells)
    assert "| risk | ROC-AUC of critical frames (THW < 1.5 s) |" in md
    assert "[0.790, 0.880]" in md
    # parameters, stage times and the metrics dump: each in a closed <details>, after the results
    for title in ("This run: parameters, machine", "Appendix — every metrics file"):
        m = re.search(f"<details><summary>{re.escape(title)} \\(click to open\\)</summary>", page)
        assert m, title
        assert m.start() > page.index("<strong>Headline results (")
    appendix = page[page.index('<h2 id="appendix--every-metrics-file">') :]
    assert "reports/metrics/extra.json" in appendix and "</details>" in appendix
    assert "<details" not in page[: page.index("<strong>Headline results (")]
    assert "<details><summary>Appendix — every metrics file (click to open)</summary>" in page_md(
        reports, "appendix"
    )
    assert page.startswith("<!DOCTYPE html>") and '<meta charset="utf-8"/>' in page


# --------------------------------------------------------------------------- zoomed score figures
def test_zoomed_limits_hand_cases() -> None:
    assert SF.zoomed_limits(np.array([0.9, 1.0])) == pytest.approx((0.885, 1.0))  # capped at 1
    assert SF.zoomed_limits(np.array([0.5, 0.7])) == pytest.approx((0.47, 0.73))
    lo, hi = SF.zoomed_limits(np.array([0.999, 0.999, np.nan]))  # one value: the minimum span
    assert hi == 1.0 and lo == pytest.approx(0.99)
    assert SF.zoomed_limits(np.array([np.nan])) == (0.0, 1.0)


def _scores() -> pd.DataFrame:
    rows = []
    for c, r, a in (("A", 0.0, 0), ("D", 5.0, 20)):
        for meth, v in (
            ("dnn", 0.998 if c == "A" else 0.996),
            ("naive", 1.0 if c == "A" else 0.97),
        ):
            for metric in ("precision", "recall", "Dice"):
                rows.append((c, r, a, meth, "free", metric, v))
                rows.append((c, r, a, meth, "occupied", metric, v - 0.2))
    return pd.DataFrame(
        rows,
        columns=["config", "noise_r_m", "noise_alpha_deg", "method", "class", "metric", "value"],
    )


def test_score_figure_zooms_each_panel_and_labels_configurations() -> None:
    import matplotlib.pyplot as plt

    from traffictwin.fusion.figures import _style

    fig = SF.score_figure(_scores(), CONFS, "free")
    try:
        axes = fig.axes
        assert [ax.get_ylabel() for ax in axes] == [
            "precision (free cells)",
            "recall (free cells)",
            "Dice (free cells)",
        ]
        for ax in axes:
            lo, hi = ax.get_ylim()
            assert 0.9 < lo < 0.97 and hi == 1.0  # zoomed on 0.97 ... 1.0, not 0 ... 1.02
            assert [t.get_text() for t in ax.get_xticklabels()] == [
                "A\nr 0 m\nα 0°",
                "D\nr 5 m\nα 20°",
            ]
            assert "r, α" in ax.get_xlabel()
            lines = {ln.get_gid(): ln for ln in ax.get_lines()}
            assert set(lines) == {"dnn", "naive"}
            assert lines["naive"].get_ydata().tolist() == [1.0, 0.97]  # the data it was given
        legend = fig.legends[0]
        labels = [t.get_text() for t in legend.get_texts()]
        assert labels == [_style(m)["label"] for m in ("dnn", "naive")]  # one entry per method
    finally:
        plt.close(fig)


# --------------------------------------------------------------------------- mass colours
def test_mass_colour_map_pure_cells_and_legend() -> None:
    m = np.zeros((2, 1, 4))
    m[0, 0, 0] = 1.0  # free
    m[1, 0, 1] = 1.0  # occupied
    m[:, 0, 3] = 0.5  # split between free and occupied, u = 0
    rgb = C.masses_to_rgb(m)
    assert rgb.shape == (1, 4, 3)
    np.testing.assert_allclose(rgb[0, 0], C.FREE)
    np.testing.assert_allclose(rgb[0, 1], C.OCC)
    np.testing.assert_allclose(rgb[0, 2], C.UNKNOWN)  # no mass: unknown
    np.testing.assert_allclose(rgb[0, 3], (C.FREE + C.OCC) / 2)
    bgr = C.masses_to_bgr8(m)
    assert bgr.dtype == np.uint8 and tuple(bgr[0, 1]) == tuple(
        np.round(C.OCC[::-1] * 255).astype(int)
    )
    assert [h.get_label() for h in C.legend_handles()] == [
        "free (m_F = 1)",
        "occupied (m_O = 1)",
        "unknown (u = 1)",
    ]
    with pytest.raises(ValueError, match=r"shape \(2, H, W\)"):
        C.masses_to_rgb(np.zeros((3, 2, 2)))


def test_cli_preview_and_data_figure_use_the_same_colours() -> None:
    from traffictwin.cli import mass_panels
    from traffictwin.fusion import data_figure

    m = np.zeros((2, 2, 2))
    m[1] = 1.0  # all occupied
    img = mass_panels([(m, None)])
    assert tuple(img[0, 0]) == tuple(C.masses_to_bgr8(m)[0, 0])  # BGR of the shared map
    # below the map: the legend strip, with a swatch of every legend colour
    strip = img[-22:]
    assert strip.shape == (22, img.shape[1], 3) and img.shape[0] == 2 * 192 + 22
    for _, colour in C.LEGEND:
        bgr = np.round(colour[::-1] * 255).astype(np.uint8)
        assert (strip == bgr).all(axis=-1).sum() >= 100, colour
    # the data figure draws with the shared map (no colours of its own)
    assert data_figure.show_masses is C.show_masses
    assert not hasattr(data_figure, "masses_to_rgb")


def test_span_cell_hand_cases() -> None:
    """An interval cell: both bounds in the format, the raw bounds kept for the checks, and n/a
    with the reason when a bound is missing or not finite."""
    from traffictwin.report.model import NA, span_cell

    cell = span_cell(0.25, 0.5, "pct", "95 % x interval, metrics/a.json#k_ci")
    assert (cell.text, cell.value) == ("[25.00 %, 50.00 %]", [0.25, 0.5])
    assert cell.derived == "95 % x interval, metrics/a.json#k_ci"
    assert span_cell(1234.5, 2000, "g4", "d").text == "[1234, 2000]"  # 4 significant digits
    for lo, hi in ((None, 1.0), (0.1, float("nan")), (float("inf"), 2.0)):
        missing = span_cell(lo, hi, "g4", "d", why="no interval in reports/metrics/a.json: k")
        assert (missing.text, missing.title) == (NA, "no interval in reports/metrics/a.json: k")
