"""Findings of the risk evaluation as markdown bullets, generated from ``reports/metrics/risk.json``.

:func:`findings` is called by the report stage (``traffictwin.risk.report_section``); every
number comes from the metrics dict (layout: :mod:`traffictwin.risk.evaluation`), nothing is typed
by hand. Missing entries (a variant or a baseline not evaluated, a metric undefined → ``None``)
are skipped, never invented.

Rules: a difference between two predictors is *claimed* ("X beats Y: +0.05 [0.02, 0.08]") only
when its paired sequence-bootstrap interval excludes zero (:func:`traffictwin.stats.excludes_zero`);
otherwise the text says "no significant difference" with the interval. A collapsed model (one
output for every frame) is listed as a failed run and never interpreted. The corridor rule on
ground-truth disparity sees perfect stereo but a straight corridor: a reference, not an oracle.

What the findings state is computed in :mod:`traffictwin.risk.findings_data`
(:class:`~traffictwin.risk.findings_data.RiskFindings`: the metrics entries to quote, verdicts,
flags, names); this module renders it: the sentences, and the formats of their numbers, are in
``templates/findings.md.j2`` (one bullet per block) and ``templates/claim.md.j2`` (one comparison)
next to it.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from traffictwin.nested import lookup
from traffictwin.report.prose import render_prose, template_macro
from traffictwin.risk.evaluation import PAPER
from traffictwin.risk.findings_data import findings_record
from traffictwin.risk.findings_values import claim_record, formatted, percent, with_ci

TEMPLATES = Path(__file__).parent / "templates"
#: the template's helpers: the number formats ``ci(entry, key, fmt, pct)`` (value [lo, hi]),
#: ``pct(share)``, ``num(x, fmt)`` ("n/a" where a number is missing) and ``get(entry, dotted key)``
HELPERS = {"ci": with_ci, "pct": percent, "num": formatted, "get": lookup}
#: the paper's numbers the findings quote, with the critical share and the stereo-pair check's
#: drop share of its data set (76,789 critical of its frames; 110,152 frames before the check)
PAPER_QUOTED = {
    **PAPER,
    "critical_share": 76789 / PAPER["n_frames"],
    "dropped_share": 1 - PAPER["n_frames"] / 110152,
}


def claim(diff: Mapping[str, Any] | None, metric: str, name: str, a: str, b: str) -> str:
    """One comparison sentence for the paired difference ``a − b`` of dotted ``metric``
    (``at_1.5s.roc_auc`` or ``test/mse``): a claim when its interval excludes zero, else "no significant difference"."""
    sentence = template_macro(TEMPLATES, "claim.md.j2", "claim")
    return str(sentence(claim_record(diff, metric, name, a, b)))


def findings(metrics: Mapping[str, Any]) -> str:
    """Markdown bullet list: paper comparison, the shipped predictor, learned model vs rule
    (claims only where the CI excludes zero), failed runs, seeds, the speed-only baseline's
    critical speed, the region effect, situations, data (the baselines' scores, the paired
    differences, the critical shares and the targets: the report's tables)."""
    record = findings_record(metrics)
    text = render_prose(TEMPLATES, "findings.md.j2", f=record, paper=PAPER_QUOTED, **HELPERS)
    return text.rstrip("\n")
