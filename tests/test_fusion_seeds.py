"""Seed replicates of the fusion claims (traffictwin.fusion.evaluation.seeds): the seeds ×
scenarios bootstrap on hand-computed cases, its reduction to the single-seed intervals, the
checks on the runs, and the report's table and bullets from the collected file."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from traffictwin.fusion.evaluation.intervals import paired_intervals
from traffictwin.fusion.evaluation.seeds import (
    PAIR_COLUMNS,
    SeedBootstrap,
    pair_table,
    seed_replicates,
)
from traffictwin.fusion.report_section.seed_tables import (
    SEEDS_FILE,
    seed_diff_table,
    seed_row_table,
    single_seed_note,
)
from traffictwin.report.model import ReportInputs, Sources
from traffictwin.stats import CIConfig

CI = CIConfig(n_boot=2000, seed=0, level=0.95)


def _samples(shift: float = 0.0, n_scen: int = 12) -> pd.DataFrame:
    """Per-pair samples of every compared row at B and D: 3 pairs per scenario; the seed rows'
    KLD(b) = the registered row's + 0.01 + ``shift``; learned fails on pair 0 of each scenario
    (pair_id % 4 == 0), registered on every odd pair_id."""
    rng = np.random.default_rng(5)
    rows = []
    for cfg in ("B", "D"):
        for s in range(n_scen):
            for k in range(3):
                pid = 1000 * s + k
                base = float(rng.uniform(0.02, 0.06))
                tp, fp, fn = (int(x) for x in rng.integers(50, 100, 3))
                for method in ("registered", "naive", "dnn", "learned", "learned+network"):
                    seedy = method not in ("registered", "naive")
                    kld = (
                        base + (0.2 if method == "naive" else 0.0) + (0.01 + shift if seedy else 0)
                    )
                    succ = np.nan
                    if method == "learned":
                        succ = float(pid % 4 != 0)
                    elif method == "registered":
                        succ = float(pid % 2 == 0)
                    rows.append((cfg, method, pid, kld, tp, fp, fn, succ))
    d = pd.DataFrame(rows, columns=list(PAIR_COLUMNS))
    return d.assign(kld_fo=d.kld_fou)  # a column the seed comparison does not read


def test_two_seeds_without_scenario_spread_give_the_seed_mixture_interval() -> None:
    # every pair 1.0 in seed 0, 3.0 in seed 1: a resample's mean is 1, 2 or 3 (seed draws
    # {0,0}, {0,1}, {1,1} with probability 1/4, 1/2, 1/4): the 95 % interval is [1, 3]
    pid = np.array([0, 1, 1000, 1001, 2000])
    plan = SeedBootstrap.plan(pid, 2, CI)
    per_seed, boot = plan.mean(np.array([[1.0] * 5, [3.0] * 5]))
    assert per_seed.tolist() == [1.0, 3.0]
    assert set(np.round(boot, 9)) == {1.0, 2.0, 3.0}
    assert abs(np.mean(boot == 2.0) - 0.5) < 0.05
    iv = plan.interval(per_seed, boot)
    assert (iv.estimate, iv.lo, iv.hi) == (2.0, 1.0, 3.0)


def test_pooled_dice_per_seed_by_hand() -> None:
    # seed 0: tp 3+1, fp 1+0, fn 0+1 -> 2*4 / (8 + 1 + 1) = 0.8; seed 1: tp 2, fp 2, fn 0 -> 4 / 6
    plan = SeedBootstrap.plan(np.array([0, 1000]), 2, CI)
    est, boot = plan.dice(
        np.array([[3, 1], [1, 1]]), np.array([[1, 0], [1, 1]]), np.array([[0, 1], [0, 0]])
    )
    assert est == pytest.approx([0.8, 2 / 3])
    assert np.all((boot >= 0.5 - 1e-12) & (boot <= 1.0 + 1e-12))


def test_one_seed_reproduces_the_single_seed_paired_intervals() -> None:
    d = _samples()
    out = seed_replicates({"default": d, "copy": d}, CI, ["B", "D"])
    e = out["findings"]["dnn_vs_registered"]["kld_fou_mean"]["D"]
    # identical runs: the seeds interval is the single-seed one, which is evaluate_fusion's
    assert e["seeds"] == e["single_seed"] and e["holds"]
    a = d[(d.config == "D") & (d.method == "dnn")].reset_index(drop=True)
    b = d[(d.config == "D") & (d.method == "registered")].reset_index(drop=True)
    ivs, n = paired_intervals(a.drop(columns="reg_success"), b.drop(columns="reg_success"), CI)
    assert n == 36
    assert e["single_seed"]["estimate"] == pytest.approx(ivs["kld_fou_mean"].estimate)
    assert e["single_seed"]["lo"] == pytest.approx(ivs["kld_fou_mean"].lo)
    assert e["single_seed"]["hi"] == pytest.approx(ivs["kld_fou_mean"].hi)
    assert e["single_seed"]["verdict"] == "higher"  # dnn = registered + 0.01 on every pair


def test_seed_spread_widens_the_interval_and_can_change_a_verdict() -> None:
    runs = {"default": _samples(), "s1": _samples(shift=-0.02), "s2": _samples(shift=-0.02)}
    out = seed_replicates(runs, CI, ["B", "D"])
    row = out["rows"]["D"]["dnn"]["kld_fou_mean"]
    assert row["per_seed"][1] == pytest.approx(row["per_seed"][0] - 0.02)
    assert row["seed_sd"] == pytest.approx(np.std([0.0, -0.02, -0.02], ddof=1))
    e = out["findings"]["dnn_vs_registered"]["kld_fou_mean"]["D"]
    # seed 0: +0.01 on every pair (higher); seeds: +0.01, -0.01, -0.01 -> mean -0.0033, the
    # interval spans the seed mixture [-0.01, +0.01]: no difference shown
    assert e["single_seed"]["verdict"] == "higher"
    assert e["seeds"]["estimate"] == pytest.approx(-0.01 / 3)
    assert e["seeds"]["lo"] == pytest.approx(-0.01) and e["seeds"]["hi"] == pytest.approx(0.01)
    assert e["seeds"]["verdict"] == "no difference shown" and not e["holds"]
    # a pose row's success rate per seed; registered is the same in every run
    s = out["rows"]["D"]["learned"]["success_rate"]
    assert s["per_seed"] == pytest.approx([2 / 3] * 3)  # pair k = 0 of each scenario fails
    assert "registered" not in out["rows"]["D"]


def test_runs_must_share_their_test_pairs_and_columns() -> None:
    d = _samples()
    other = d[d.pair_id != 0]
    with pytest.raises(ValueError, match="seed run 's1': row 'dnn' at configuration B has other"):
        seed_replicates({"default": d, "s1": other}, CI, ["B", "D"])
    with pytest.raises(ValueError, match=r"s1: missing column\(s\) \['kld_fou'\]"):
        seed_replicates({"default": d, "s1": d.drop(columns="kld_fou")}, CI, ["B"])
    with pytest.raises(ValueError, match="at least 2 runs"):
        seed_replicates({"default": d}, CI, ["B"])
    assert list(pair_table(d).columns) == list(PAIR_COLUMNS)


def _sources(tmp_path, seeds: dict | None) -> Sources:
    if seeds is not None:
        (tmp_path / "ablations").mkdir()
        (tmp_path / SEEDS_FILE).write_text(json.dumps(seeds))
    return Sources(ReportInputs(reports_dir=tmp_path, profile="ci", seed=1, git_commit="x"))


def test_report_says_single_seed_until_the_replicates_are_collected(tmp_path) -> None:
    src = _sources(tmp_path, None)
    assert "one training seed" in single_seed_note(src).lower()
    assert seed_row_table(src) is None and seed_diff_table(src) is None


def test_report_shows_each_row_and_finding_of_the_replicates(tmp_path) -> None:
    runs = {"default": _samples(), "s1": _samples(shift=-0.02), "s2": _samples(shift=-0.02)}
    src = _sources(tmp_path, seed_replicates(runs, CI, ["B", "D"]))
    assert single_seed_note(src) is None
    t = seed_row_table(src)
    cells = {(r[0].text, r[1].text, r[2].text): r for r in t.rows}
    r = cells[("D", "dnn", "KLD(b)")]
    assert r[3].src == f"{SEEDS_FILE}#rows.D.dnn.kld_fou_mean.estimate"
    assert r[5].text.count(",") == 2  # three seeds' values
    assert ("D", "learned", "success") in cells
    diffs = {(r[0].text, r[1].text, r[2].text): r for r in seed_diff_table(src).rows}
    d = diffs[("dnn − registered", "KLD(b)", "D")]
    assert [c.text for c in d[3:]] == [
        "-0.003333",
        "[-0.01, 0.01]",
        "no difference shown",
        "higher",
    ]
    assert d[3].src == f"{SEEDS_FILE}#findings.dnn_vs_registered.kld_fou_mean.D.seeds.estimate"
    b = diffs[("dnn − registered", "KLD(b)", "B")]
    assert b[5].text != b[6].text  # the verdict changes with seeds at B, as at D
