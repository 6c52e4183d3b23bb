"""The verdicts on the report's first screen: each paper claim against this run's numbers, decided
by the interval rule (a difference is a finding only when its 95 % interval excludes zero), on
hand-made numbers: reproduced, exceeded, not reproduced, not comparable."""

from __future__ import annotations

import pytest

from traffictwin import paper_numbers as P
from traffictwin.fusion.findings import verdict
from traffictwin.fusion.report_section.claims import fusion_claims
from traffictwin.interval_rule import interval_side
from traffictwin.report.claims import (
    EXCEEDED,
    NOT_COMPARABLE,
    NOT_REPRODUCED,
    REPRODUCED,
    VERDICTS,
    claim_verdict,
    fmt_interval,
)
from traffictwin.risk.report_section import claims as risk_claims


def test_interval_side_against_zero_a_value_and_an_interval() -> None:
    assert interval_side(-0.3, -0.1) == "lower"
    assert interval_side(0.1, 0.3) == "higher"
    assert interval_side(-0.1, 0.2) == "no difference shown"
    assert interval_side(0.0, 0.2) == "no difference shown"  # touching zero is no finding
    assert interval_side(None, 0.2) == "n/a" and interval_side(float("nan"), 1.0) == "n/a"
    assert interval_side(0.8, 0.9, 0.7287) == "higher"  # against a paper's printed value
    assert interval_side(0.70, 0.75, 0.7287) == "no difference shown"
    assert interval_side(-0.3, -0.2, -0.1, 0.0) == "lower"  # against another interval
    assert interval_side(-0.3, -0.05, -0.1, 0.0) == "no difference shown"  # they overlap
    assert interval_side(0.1, 0.3, None) == "n/a"  # no reference: nothing to place against
    assert interval_side(True, 0.3) == "n/a"  # a flag is no bound


@pytest.mark.parametrize(
    ("lo", "hi"),
    [(-0.3, -0.1), (0.1, 0.3), (-0.1, 0.2), (0.0, 0.2), (-0.2, 0.0), (None, 0.2), (0.1, "x")],
)
def test_fusion_findings_and_claims_place_a_difference_by_the_same_rule(lo, hi) -> None:
    """The fusion findings' verdict of a paired difference is the interval rule against zero."""
    assert verdict({"estimate": 0.0, "lo": lo, "hi": hi}) == interval_side(lo, hi)
    assert verdict(None) == "n/a"


def test_claim_verdict_each_verdict_on_hand_made_sides() -> None:
    assert VERDICTS == (REPRODUCED, EXCEEDED, NOT_REPRODUCED, NOT_COMPARABLE)
    # a claimed difference: every interval on the claimed side; beyond it is no "exceeded"
    assert claim_verdict(["lower", "lower", "lower"], "lower") == REPRODUCED
    assert claim_verdict(["higher"], "higher") == REPRODUCED
    assert claim_verdict(["lower", "higher", "lower"], "lower") == NOT_REPRODUCED
    assert claim_verdict(["lower", "no difference shown"], "lower") == NOT_REPRODUCED
    assert claim_verdict(["lower", "n/a"], "lower") == NOT_COMPARABLE
    assert claim_verdict([], "higher") == NOT_COMPARABLE
    # a paper's number: reproduced when our interval reaches it ...
    assert claim_verdict(["no difference shown"], "higher", value=True) == REPRODUCED
    assert claim_verdict(["no difference shown"], "lower", value=True) == REPRODUCED
    # ... exceeded when every interval lies wholly beyond it on the better side ...
    assert claim_verdict(["higher"], "higher", value=True) == EXCEEDED
    assert claim_verdict(["lower", "lower"], "lower", value=True) == EXCEEDED
    # ... reproduced when some reach it and the others lie beyond; else not reproduced
    assert claim_verdict(["higher", "no difference shown"], "higher", value=True) == REPRODUCED
    assert claim_verdict(["lower"], "higher", value=True) == NOT_REPRODUCED
    assert claim_verdict(["higher", "lower"], "higher", value=True) == NOT_REPRODUCED
    assert claim_verdict(["n/a"], "higher", value=True) == NOT_COMPARABLE
    with pytest.raises(ValueError, match="expected must be 'lower' or 'higher'"):
        claim_verdict(["lower"], "better")


def test_fmt_interval() -> None:
    assert fmt_interval(-0.131, -0.153, -0.111) == "-0.131 [-0.153, -0.111]"
    assert fmt_interval(0.5, None, 0.6) == "+0.5"  # no interval: the estimate alone
    assert fmt_interval(None, None, None) == "n/a"


def _fusion(diffs: dict[str, tuple[float, float]], dice: dict[str, tuple[float, float]]) -> dict:
    """fusion.json with the paired intervals of network − naive (``(lo, hi)`` per configuration)
    on KLD(b) and occupied Dice, and quartiles for the spread."""
    test = {
        c: {
            row: {"kld_fou_mean": 0.1, "kld_fou_q25": 0.05, "kld_fou_q75": q75}
            for row, q75 in (("dnn", 0.1), ("naive", 0.3))
        }
        for c in diffs
    }
    diff = {
        c: {
            "dnn": {
                "vs_naive": {
                    "kld_fou_mean": {
                        "estimate": sum(diffs[c]) / 2,
                        "lo": diffs[c][0],
                        "hi": diffs[c][1],
                    },
                    "dice_occ": {"estimate": sum(dice[c]) / 2, "lo": dice[c][0], "hi": dice[c][1]},
                }
            }
        }
        for c in diffs
    }
    return {"fusion.json": {"test": test, "diff": diff}}


def test_fusion_claims_as_the_paper_says() -> None:
    """The paper's picture: naive better at A, the network better from B on, the gap growing."""
    m = _fusion(
        {"A": (0.001, 0.002), "B": (-0.15, -0.1), "C": (-0.2, -0.15), "D": (-0.25, -0.2)},
        {"A": (-0.004, -0.002), "B": (0.05, 0.07), "C": (0.08, 0.09), "D": (0.09, 0.1)},
    )
    got = {c.claim: c for c in fusion_claims(m)}
    assert list(got) == [c.text for c in P.FUSION_CLAIMS.values()]
    v = {k: got[c.text].verdict for k, c in P.FUSION_CLAIMS.items()}
    assert v == {
        "kld_A_baseline_better": REPRODUCED,
        "kld_BCD_net_better": REPRODUCED,
        "kld_baseline_degrades_faster": REPRODUCED,
        "kld_net_less_spread": NOT_COMPARABLE,  # no interval for the spread
        "scores_A_baseline_better": REPRODUCED,
        "scores_flatter_net": REPRODUCED,
        "scores_net_dominant_except": REPRODUCED,
    }
    c = got[P.FUSION_CLAIMS["kld_BCD_net_better"].text]
    assert c.paper == "Paper 1 — fusion" and c.where == "Sec. V-A, Fig. 5"
    assert "B -0.125 [-0.15, -0.1]" in c.measured and "D -0.225 [-0.25, -0.2]" in c.measured
    spread = got[P.FUSION_CLAIMS["kld_net_less_spread"].text].measured
    assert "B 0.05 vs 0.25" in spread


def test_fusion_claims_not_reproduced_and_not_comparable() -> None:
    """The network better at A, no difference shown at C and D (intervals contain 0), the gaps
    not grown (intervals overlap); a missing paired difference: not comparable."""
    m = _fusion(
        {"A": (-0.002, -0.001), "B": (-0.15, -0.1), "C": (-0.01, 0.02), "D": (-0.01, 0.0)},
        {"A": (0.001, 0.003), "B": (-0.01, 0.01), "C": (0.0, 0.01), "D": (0.002, 0.004)},
    )
    v = {c.claim: c.verdict for c in fusion_claims(m)}
    T = {k: c.text for k, c in P.FUSION_CLAIMS.items()}
    assert v[T["kld_A_baseline_better"]] == NOT_REPRODUCED  # the network is better at A
    assert v[T["kld_BCD_net_better"]] == NOT_REPRODUCED  # no difference shown at C, D
    assert v[T["kld_baseline_degrades_faster"]] == NOT_REPRODUCED  # D's gap overlaps A's
    assert v[T["scores_A_baseline_better"]] == NOT_REPRODUCED
    assert v[T["scores_flatter_net"]] == NOT_REPRODUCED  # [0.002, 0.004] overlaps [0.001, 0.003]
    assert v[T["scores_net_dominant_except"]] == NOT_REPRODUCED
    del m["fusion.json"]["diff"]["B"]  # no paired difference at B: nothing to decide on
    v = {c.claim: c.verdict for c in fusion_claims(m)}
    assert v[T["kld_BCD_net_better"]] == NOT_COMPARABLE
    assert fusion_claims({}) == [] and fusion_claims({"fusion.json": {"test": {}}}) == []


def _risk(acc: tuple[float, float, float], mse: tuple[float, float, float]) -> dict:
    row = {
        "at_1.5s": {"accuracy": acc[0], "accuracy_ci": {"lo": acc[1], "hi": acc[2]}},
        "test/mse": mse[0],
        "test/mse_ci": {"lo": mse[1], "hi": mse[2]},
    }
    return {
        "risk.json": {
            "main_variant": "headline",
            "models": {"paper": row, "headline": {}},
            "n_frames": {"total": 1000, "orb_outliers_dropped": 40},
        }
    }


def test_risk_claims_against_the_papers_numbers() -> None:
    # accuracy 0.80 [0.75, 0.85] wholly above 72.87 %: exceeded; above Wang & Kato's 70.77 %: the
    # claimed lead (a difference) reproduced; MSE interval contains 0.0147: reproduced
    got = risk_claims(_risk((0.80, 0.75, 0.85), (0.015, 0.012, 0.018)))
    assert [c.verdict for c in got] == [EXCEEDED, REPRODUCED, REPRODUCED, NOT_COMPARABLE]
    assert [c.where for c in got] == ["Sec. 4, Table 1", "Sec. 4", "Sec. 4 (ref. [20])", "Sec. 3.3"]
    assert got[0].measured == "accuracy 80.00 % [75.00 %, 85.00 %] (network `paper`, test frames)"
    assert got[3].measured.startswith("4.00 % of 1,000 pairs dropped")
    # accuracy 0.73 [0.70, 0.76] reaches 72.87 %: reproduced; MSE [0.008, 0.012] wholly below
    # 0.0147 (an error: lower is better): exceeded; [0.70, 0.76] contains 70.77 %: no lead shown
    got = risk_claims(_risk((0.73, 0.70, 0.76), (0.01, 0.008, 0.012)))
    assert [c.verdict for c in got][:3] == [REPRODUCED, EXCEEDED, NOT_REPRODUCED]
    # accuracy 0.71 [0.69, 0.72]: below 72.87 %, Wang & Kato's 70.77 % inside: no lead shown;
    # MSE [0.02, 0.03] above the paper's 0.0147
    got = risk_claims(_risk((0.71, 0.69, 0.72), (0.025, 0.02, 0.03)))
    assert [c.verdict for c in got][:3] == [NOT_REPRODUCED, NOT_REPRODUCED, NOT_REPRODUCED]
    # no interval: not comparable; no model at all: no claims
    no_ci = _risk((0.8, 0.75, 0.85), (0.015, 0.012, 0.018))
    del no_ci["risk.json"]["models"]["paper"]["at_1.5s"]["accuracy_ci"]
    assert risk_claims(no_ci)[0].verdict == NOT_COMPARABLE
    assert risk_claims({}) == []
