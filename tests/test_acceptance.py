"""Acceptance thresholds: one judge (hand cases per operator, the interval rule, the second
condition, missing figures), the config's validation, the config reaching the verdicts, and no
threshold left in the targets modules."""

from __future__ import annotations

import ast
import dataclasses
import math
from pathlib import Path

import pytest
from _acceptance import thresholds
from conftest import composed

from traffictwin.acceptance import (
    FAIL,
    NOT_EVALUATED,
    PASS,
    Condition,
    Threshold,
    for_problem,
    judge,
)
from traffictwin.acceptance import thresholds as build
from traffictwin.config import ConfigError, compose_config

ROOT = Path(__file__).resolve().parents[1]


def _t(op: str, value: float, **kw) -> Threshold:
    return Threshold(op, value, name="x", metric="m", **kw)


# --------------------------------------------------------------------------- judge
@pytest.mark.parametrize(
    ("op", "estimate", "status"),
    [
        ("<=", 0.3, PASS),  # on the threshold
        ("<=", 0.31, FAIL),
        ("<", 0.3, FAIL),
        ("<", 0.29, PASS),
        (">=", 0.3, PASS),
        (">=", 0.29, FAIL),
        (">", 0.3, FAIL),
        (">", 0.31, PASS),
    ],
)
def test_each_operator_on_the_estimate(op: str, estimate: float, status: str) -> None:
    j = judge(_t(op, 0.3), estimate, estimate - 0.1, estimate + 0.1)
    assert j.status == status and j.met is (status == PASS)


def test_whether_the_interval_lies_beyond_the_threshold() -> None:
    le = _t("<=", 0.3)
    # a pass whose interval reaches over the threshold is not beyond it
    assert judge(le, 0.2, 0.1, 0.25).ci_beyond and judge(le, 0.2, 0.1, 0.25).ci_passes
    assert not judge(le, 0.2, 0.1, 0.35).ci_beyond
    # a fail wholly above the threshold is beyond it (on the fail side), and does not pass
    j = judge(le, 0.5, 0.4, 0.6)
    assert j.status == FAIL and j.ci_beyond and not j.ci_passes
    ge = _t(">=", 0.85)
    assert not judge(ge, 0.8, 0.7, 0.9).ci_beyond
    assert judge(ge, 0.8, 0.7, 0.84).ci_beyond
    # a missing end: nothing beyond
    assert not judge(ge, 0.9, None, None).ci_beyond


def test_judged_on_the_interval_or_one_end() -> None:
    above0 = _t(">", 0.0, judged_on="interval")  # the lower end must be above 0
    assert judge(above0, 0.03, 0.01, 0.05).status == PASS
    assert judge(above0, 0.03, -0.01, 0.07).status == FAIL
    assert judge(above0, 0.03, 0.0, 0.07).status == FAIL  # strict
    assert judge(above0, 0.03, None, None).status == FAIL  # no interval: not shown
    below0 = _t("<", 0.0, judged_on="interval")  # the upper end must be below 0
    assert judge(below0, -0.05, -0.08, -0.001).status == PASS
    assert judge(below0, -0.05, -0.08, 0.01).status == FAIL
    hi = _t("<=", 0.005, judged_on="hi")  # the upper bound itself
    assert judge(hi, 0.001, -0.001, 0.003).status == PASS
    assert judge(hi, 0.001, -0.001, 0.006).status == FAIL
    assert judge(hi, 0.001, -0.001, None).status == NOT_EVALUATED
    lo = _t("<=", 0.0, judged_on="lo")  # not shown worse: the lower end at or below 0
    assert judge(lo, 0.02, 0.0, 0.04).status == PASS
    assert judge(lo, 0.02, 0.01, 0.04).status == FAIL


def test_the_second_condition_on_the_lower_end() -> None:
    gain = _t(">=", 0.10, also=Condition(">=", 0.05, "lo"))
    assert judge(gain, 0.12, 0.06, 0.2).status == PASS
    j = judge(gain, 0.12, 0.03, 0.2)  # the estimate passes, the lower end does not
    assert j.status == FAIL and j.met is False
    assert not j.ci_beyond  # beyond is about the main condition: the interval reaches below 0.10
    assert judge(gain, 0.12, None, 0.2).status == FAIL
    assert judge(gain, 0.08, 0.06, 0.2).status == FAIL
    lead = _t(">=", 0.8, also=Condition(">", 0.0, "lo"))
    assert judge(lead, 0.9, 0.1, 1.2).status == PASS
    assert judge(lead, 0.9, 0.0, 1.2).status == FAIL
    assert gain.text == ">= 0.1 and lower end >= 0.05"


@pytest.mark.parametrize("estimate", [None, math.nan, math.inf, "0.1"])
def test_a_missing_figure_is_not_evaluated(estimate) -> None:
    j = judge(_t("<=", 0.3), estimate, 0.1, 0.2)
    assert (j.status, j.met, j.ci_beyond, j.ci_passes) == (NOT_EVALUATED, None, False, False)


# --------------------------------------------------------------------------- configuration
def test_the_config_group_builds_every_problem() -> None:
    for problem in ("fusion", "risk", "stereo", "twin"):
        th = thresholds(problem)
        assert th and all(isinstance(t, Threshold) and t.name == n for n, t in th.items())
    f = thresholds("fusion")
    assert (f["kld_ratio_vs_naive"].operator, f["kld_ratio_vs_naive"].value) == ("<=", 0.3)
    assert f["kld_ratio_vs_naive"].configs == ("C", "D")
    assert f["learned_success_gain_at_D"].also == Condition(">=", 0.05, "lo")
    assert isinstance(f["dice_occ_vs_ego"].value, float)  # 0.0, not 0: the metrics files' bytes


def test_the_spread_threshold_is_the_collapse_limit() -> None:
    cfg = composed("profile=ci", "evaluation.risk.collapse_std=0.02")
    assert for_problem(cfg, "risk")["spread"].value == 0.02


@pytest.mark.parametrize(
    ("entry", "message"),
    [
        ({"metric": "m", "value": 1.0}, r"'acceptance.fusion.x.operator' is missing"),
        ({"metric": "m", "operator": "<="}, r"'acceptance.fusion.x.value' is missing"),
        ({"metric": "m", "operator": "=<", "value": 1.0}, r"'acceptance.fusion.x.operator' must"),
        ({"metric": "m", "operator": "<=", "value": "a"}, r"'acceptance.fusion.x.value' must be a"),
        ({"metric": "m", "operator": "<=", "value": math.nan}, r"'acceptance.fusion.x.value'"),
        ({"metric": "m", "operator": "<=", "value": True}, r"'acceptance.fusion.x.value'"),
        ({"operator": "<=", "value": 1.0}, r"'acceptance.fusion.x.metric'"),
        (
            {"metric": "m", "operator": "<=", "value": 1.0, "judged_on": "mean"},
            r"'acceptance.fusion.x.judged_on' must be one of",
        ),
        (
            {"metric": "m", "operator": "<=", "value": 1.0, "also": {"operator": ">"}},
            r"'acceptance.fusion.x.also.value' is missing",
        ),
        (
            {"metric": "m", "operator": "<=", "value": 1.0, "thresold": 2},
            r"'acceptance.fusion.x': unknown field.*thresold",
        ),
        ({"metric": "m", "operator": "<=", "value": 1.0, "configs": "C"}, r"x.configs' must be"),
    ],
)
def test_a_bad_threshold_names_its_key(entry: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        build({"x": entry}, "acceptance.fusion")


def test_the_names_must_match_the_targets_judged() -> None:
    ok = {"metric": "m", "operator": "<=", "value": 1.0}
    with pytest.raises(ConfigError, match=r"no threshold for \['b'\]"):
        build({"a": ok}, "acceptance.twin", names=["a", "b"])
    with pytest.raises(ConfigError, match=r"unknown target\(s\) \['c'\]"):
        build({"a": ok, "c": ok}, "acceptance.twin", names=["a"])
    with pytest.raises(ConfigError, match="'acceptance.risk' is missing"):
        for_problem({"acceptance": {}}, "risk")


def test_check_params_rejects_a_bad_threshold() -> None:
    from omegaconf import OmegaConf

    from pipelines.check_params import check

    cfg = compose_config(
        ROOT / "conf", ["profile=ci", "acceptance.twin.occluded_recall_above_ego.operator=bad"]
    )
    with pytest.raises(ConfigError, match=r"acceptance.twin.occluded_recall_above_ego.operator"):
        check(OmegaConf.create(cfg))


# --------------------------------------------------------------------------- the config decides
def test_a_moved_threshold_moves_the_twin_and_risk_verdicts() -> None:
    from traffictwin.risk.evaluation.targets import judge as risk_judge
    from traffictwin.stats import Interval
    from traffictwin.twin.targets import targets

    s = {"twin": {"occluded": {"recall": 0.85, "recall_ci": [0.8, 0.9]}}}
    twin = thresholds("twin")
    assert targets({"D": {"methods": s}}, "twin", "D", twin)["occluded_recall"]["met"] is False
    moved = {
        **twin,
        "occluded_recall": dataclasses.replace(twin["occluded_recall"], value=0.8),
    }
    assert targets({"D": {"methods": s}}, "twin", "D", moved)["occluded_recall"]["met"] is True
    risk = thresholds("risk")
    iv = Interval(0.96, 0.9, 0.99)
    assert risk_judge(iv, risk["shipped_roc_auc"])["met"] is False  # >= 0.97
    lower = dataclasses.replace(risk["shipped_roc_auc"], value=0.95)
    assert risk_judge(iv, lower)["met"] is True and risk_judge(iv, lower)["threshold"] == 0.95


# --------------------------------------------------------------------------- no literals left
TARGET_MODULES = (
    "fusion/evaluation/targets.py",
    "risk/evaluation/targets.py",
    "stereo/targets.py",
    "twin/targets.py",
)


def _threshold_literals(path: Path) -> list[str]:
    """Float literals in ``path`` other than 0.0 / 1.0 (a threshold spelt out in code)."""
    tree = ast.parse(path.read_text())
    return [
        f"{path.name}:{n.lineno}: {n.value!r}"
        for n in ast.walk(tree)
        if isinstance(n, ast.Constant) and isinstance(n.value, float) and n.value not in (0.0, 1.0)
    ]


def test_no_targets_module_holds_a_threshold() -> None:
    src = ROOT / "src" / "traffictwin"
    hits = [h for m in TARGET_MODULES for h in _threshold_literals(src / m)]
    assert not hits, "thresholds belong in conf/acceptance:\n" + "\n".join(hits)


def test_the_literal_check_can_fail(tmp_path: Path) -> None:
    p = tmp_path / "t.py"
    p.write_text("T = {'x': (0.3, '<=')}\nok = 0.0\n")
    assert _threshold_literals(p) == ["t.py:1: 0.3"]


# --------------------------------------------------------------------------- the report's table
def _sources(tmp_path: Path, metrics: dict[str, object]):
    import json

    from traffictwin.report.model import ReportInputs, Sources

    (tmp_path / "metrics").mkdir()
    for name, data in metrics.items():
        (tmp_path / "metrics" / name).write_text(json.dumps(data))
    return Sources(ReportInputs(tmp_path, "ci", 0, "abc"))


FUSION_JSON = {
    "targets": {
        "kld_at_A": {
            "description": "network KLD(b) at A",
            "op": "<=",
            "threshold": 0.002,
            "status": "fail",
            "per_config": {"A": {"value": 0.003, "lo": 0.0025, "hi": 0.0035, "status": "fail"}},
        },
        "dice_occ_vs_ego": {
            "description": "Dice occ − ego",
            "op": ">=",
            "threshold": 0.0,
            "status": "not evaluated",
            "per_config": {
                "B": {"value": 0.1, "lo": 0.05, "hi": 0.15, "status": "pass"},
                "C": {"value": None, "status": "not evaluated", "why": "ego not evaluated"},
            },
        },
    }
}
RISK_JSON = {
    "targets": {
        "shipped_roc_auc": {
            "description": "ROC-AUC at THW 1.5 s",
            "value": 0.98,
            "lo": 0.96,
            "hi": 0.99,
            "op": ">=",
            "threshold": 0.97,
            "met": True,
        },
        "shipped_recall_cut_in": {
            "description": "recall, cut-in",
            "met": False,
            "why": "no frames",
        },
    }
}
STEREO_JSON = {
    "targets": {
        "learned_crit_obj_relerr_median": {
            "metric": "learned/own/crit_obj_relerr_median",
            "value": 0.03,
            "value_lo": 0.02,
            "value_hi": 0.04,
            "op": "<=",
            "threshold": 0.035,
            "format": "pct",
            "description": "median relative range error",
            "met": True,
        }
    }
}
TWIN_JSON = {
    "targets": {
        "configuration": "D",
        "method": "learned",
        "evaluated": True,
        "occluded_recall": {"value": 0.8, "ci": [0.7, 0.9], "met": False},
    }
}


def test_the_acceptance_table_reads_every_file_shape(tmp_path: Path) -> None:
    from traffictwin.report.acceptance import acceptance_rows, acceptance_section, count_line

    src = _sources(
        tmp_path,
        {
            "fusion.json": FUSION_JSON,
            "risk.json": RISK_JSON,
            "stereo.json": STEREO_JSON,
            "twin.json": TWIN_JSON,
        },
    )
    th = {p: thresholds(p) for p in ("fusion", "risk", "stereo", "twin")}
    rows = acceptance_rows(src, th)
    got = [[c.text for c in r.cells()] for r in rows]
    assert got[:3] == [
        [
            "fusion",
            "kld_at_A (A)",
            "network KLD(b) at A",
            "<= 0.002",
            "0.003 [0.0025, 0.0035]",
            "fail",
        ],
        ["fusion", "dice_occ_vs_ego (B)", "Dice occ − ego", ">= 0", "0.1 [0.05, 0.15]", "pass"],
        ["fusion", "dice_occ_vs_ego (C)", "Dice occ − ego", ">= 0", "n/a", "not evaluated"],
    ]
    assert rows[2].value.title == "ego not evaluated"
    assert rows[0].value.derived.endswith("metrics/fusion.json#targets.kld_at_A.per_config.A.value")
    risk = [g for g in got if g[0] == "risk"]
    assert risk == [
        ["risk", "shipped_roc_auc", "ROC-AUC at THW 1.5 s", ">= 0.97", "0.98 [0.96, 0.99]", "pass"],
        ["risk", "shipped_recall_cut_in", "recall, cut-in", ">= 0.85", "n/a", "not evaluated"],
    ]
    stereo = [g for g in got if g[0] == "stereo"]
    assert stereo == [
        [
            "stereo",
            "learned_crit_obj_relerr_median",
            "median relative range error",
            "<= 0.035",
            "3.00 % [2.00 %, 4.00 %]",
            "pass",
        ]
    ]
    twin = [g for g in got if g[0] == "twin"]
    assert twin[0][1:2] + twin[0][3:] == [
        "occluded_recall (D)",
        ">= 0.9",
        "0.8 [0.7, 0.9]",
        "fail",
    ]
    # the twin's other thresholds are absent from the block: not evaluated, never a pass
    assert len(twin) == len(th["twin"]) and all(g[5] == "not evaluated" for g in twin[1:])
    # a target a constant can meet says what the constant scores on it
    lead = {"value": -0.4, "ci": [-0.6, -0.2], "met": False, "always_warns_value": 0.171}
    twin_json = {"targets": {**TWIN_JSON["targets"], "registration_lead_above_naive": lead}}
    (tmp_path / "constant").mkdir()
    src2 = _sources(tmp_path / "constant", {"twin.json": twin_json})
    (row,) = [r for r in acceptance_rows(src2, th) if r.name == "registration_lead_above_naive"]
    assert row.description.endswith("; a warning at every frame scores 0.17 on it")
    assert count_line(rows) == f"3 pass, 2 fail, {len(rows) - 5} not evaluated"
    sec = acceptance_section(src, th)
    (table,) = sec.tables
    assert table.note.startswith(count_line(rows) + ".") and table.anchor == "acceptance"
    # fusion thresholds fusion.json does not judge (wall times) are named, not counted
    assert "learned_runtime_ms" in table.note


def test_a_missing_metrics_file_shows_its_thresholds_not_evaluated(tmp_path: Path) -> None:
    from traffictwin.report.acceptance import acceptance_rows

    src = _sources(tmp_path, {"risk.json": RISK_JSON})
    rows = acceptance_rows(src, {"stereo": thresholds("stereo")})
    stereo = [r for r in rows if r.problem == "stereo"]
    assert [r.name for r in stereo] == list(thresholds("stereo"))
    assert all(r.status == "not evaluated" for r in stereo)
    assert "stereo.json not found" in stereo[0].value.title
    # without thresholds (an old run's params): the file's own op / threshold
    assert [r.condition for r in rows if r.problem == "risk"] == [">= 0.97", "n/a"]


def test_the_index_ends_with_the_acceptance_table(tmp_path: Path) -> None:
    from pipelines.report import providers
    from traffictwin.report.model import ReportInputs
    from traffictwin.report.render import render_pages, write_report

    (tmp_path / "metrics").mkdir()
    (tmp_path / "metrics" / "stereo.json").write_text(__import__("json").dumps(STEREO_JSON))
    th = {p: thresholds(p) for p in ("fusion", "risk", "stereo", "twin")}
    inputs = ReportInputs(tmp_path, "ci", 0, "abc", acceptance=th)
    report = write_report(inputs, providers({}))
    index = render_pages(report)["README.md"]
    sections = [line for line in index.splitlines() if line.startswith("## ")]
    assert sections[-2:] == ["## Acceptance thresholds", "## Pages"]
    assert "| stereo | learned_crit_obj_relerr_median |" in index
    assert "1 pass, 0 fail," in index
    assert len(index.splitlines()) < 600
