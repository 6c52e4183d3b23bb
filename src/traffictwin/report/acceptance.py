"""The acceptance table at the end of the report's index: one row per target (and configuration)
of the metrics files' ``targets`` blocks, with the condition it must meet from the acceptance
thresholds the report stage passes in (``acceptance.<problem>``, :mod:`traffictwin.acceptance`),
and a count of the statuses."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from traffictwin.acceptance import FAIL, NOT_EVALUATED, PASS, Threshold
from traffictwin.report import model as page
from traffictwin.report.model import NA, Cell, Section, Table, fmt_value, json_number, number_cell
from traffictwin.report.summary import interval

TITLE = "Acceptance thresholds"
#: the line each problem's page shows where its targets table was (pages sit in reports/pages/);
#: the anchor is the section heading's slug
POINTER = (
    "Targets: every target's verdict against its acceptance threshold is in the "
    f"[acceptance table](../README.md#{TITLE.lower().replace(' ', '-')}) at the end of the report index."
)
ANCHOR = "acceptance"
COLUMNS = ["problem", "threshold name", "what it checks", "condition"]
COLUMNS += ["this run (value [95 % CI])", "status"]
#: the problems in report order, each with its metrics file ``<problem>.json``
PROBLEMS = ("fusion", "risk", "stereo", "twin")
#: the problems whose thresholds absent from the file's block are shown as not evaluated
LIST_ABSENT = ("twin",)

Thresholds = Mapping[str, Mapping[str, Threshold]]


@dataclass
class Row:
    """One target at one configuration (``where``: ``""`` where it has none)."""

    problem: str
    name: str
    where: str
    description: str
    condition: str
    value: Cell
    status: str

    def cells(self) -> list[Cell]:
        name = f"{self.name} ({self.where})" if self.where else self.name
        texts = (self.problem, name, self.description, self.condition)
        return [*map(Cell, texts), self.value, Cell(self.status)]


def _condition(t: Threshold | None, e: Mapping[str, Any]) -> str:
    """The threshold's condition (from the config), else the metrics file's ``op threshold``."""
    if t is not None:
        return t.text
    op, thr = e.get("op"), json_number(e.get("threshold"))
    return f"{op} {thr:g}" if op and thr is not None else NA


def _value_cell(src: page.Sources, file: str, key: str, e: Mapping[str, Any], fmt: str) -> Cell:
    """``value [lo, hi]`` of the number at ``file#key`` and the interval of its entry ``e``
    (``ci: [lo, hi]``, ``lo``/``hi`` or ``value_lo``/``value_hi``); n/a, with the entry's ``why``,
    where it is missing."""
    v, src_key = json_number(src.get(file, key)), f"{src.path(file)}#{key}"
    why = str(e.get("why", ""))
    if v is None:
        return Cell(NA, title=why or "not evaluated")
    iv = interval(e.get("ci")) or interval(
        (e.get("lo", e.get("value_lo")), e.get("hi", e.get("value_hi")))
    )
    if iv is None:
        return number_cell(v, fmt, src_key, why)
    lo, hi = iv
    text = f"{fmt_value(v, fmt)} [{fmt_value(lo, fmt)}, {fmt_value(hi, fmt)}]"
    derived = f"value and 95 % interval, {src_key}"  # a derived cell naming where both come from
    return Cell(text, value=[v, lo, hi], fmt=fmt, title=why, derived=derived)


def _ablation_verdict(src: page.Sources, key: str) -> tuple[str, str, Mapping[str, Any]] | None:
    """A fusion target this run did not evaluate, from an ablation experiment's collected results
    (``reports/ablations/<name>.json``, blocks under ``fusion.``): (file, key, entry)."""
    for f in (f for f in sorted(src.metrics) if f.startswith("ablations/")):
        found = src.get(f, f"fusion.{key}")
        if isinstance(found, dict) and found.get("value") is not None:
            return f, f"fusion.{key}", found
    return None


def fusion_rows(
    src: page.Sources, th: Mapping[str, Threshold], file: str, problem: str
) -> list[Row]:
    """fusion.json: ``targets.<name>.per_config.<cfg>: {value, lo, hi, status, why}``; a target
    this run does not evaluate shows an ablation experiment's verdict, marked as such."""
    rows = []
    for name, spec in (src.get(file, "targets") or {}).items():
        if not isinstance(spec, dict):
            continue
        desc = str(spec.get("description", "") or getattr(th.get(name), "description", ""))
        for c, e in (spec.get("per_config") or {}).items():
            f, key, status = file, f"targets.{name}.per_config.{c}", str(e.get("status", NA))
            if e.get("value") is None and (found := _ablation_verdict(src, key)):
                f, key, e = found
                status = f"{e.get('status', NA)} (ablation {src.get(f, 'name', f)})"
            value = _value_cell(src, f, f"{key}.value", e, "g4")
            rows.append(Row(problem, name, c, desc, _condition(th.get(name), spec), value, status))
    return rows


def target_rows(
    src: page.Sources, th: Mapping[str, Threshold], file: str, problem: str
) -> list[Row]:
    """risk.json, stereo.json, twin.json: ``targets.<name>: {value, met, ...}`` with its interval,
    optional ``format``, ``why``, ``description`` (else the threshold's, else ``note``) and
    ``always_warns_value`` (what a warning at every frame scores); the block's ``configuration``
    (twin) is every row's. Non-object entries (the twin's ``method``, ...) are no targets."""
    block = src.get(file, "targets") or {}
    where = str(block.get("configuration", ""))
    rows = []
    for name, e in ((n, e) for n, e in block.items() if isinstance(e, dict)):
        value = _value_cell(src, file, f"targets.{name}.value", e, str(e.get("format") or "g4"))
        t = th.get(name)
        desc = str(e.get("description") or getattr(t, "description", "") or e.get("note", ""))
        if isinstance(always := e.get("always_warns_value"), int | float):  # met by a constant?
            desc += f"; a warning at every frame scores {always:.2f} on it"
        status = PASS if e.get("met") else FAIL
        if e.get("met") is None or json_number(e.get("value")) is None:
            status = NOT_EVALUATED
        rows.append(Row(problem, name, where, desc, _condition(t, e), value, status))
    if problem in LIST_ABSENT:
        what = f"at {where} for {block.get('method', 'the headline')}" if where else ""
        rows += _absent(problem, th, {r.name for r in rows}, f"not evaluated {what}".strip(), where)
    return rows


def _absent(
    problem: str, th: Mapping[str, Threshold], seen: set[str], why: str, where: str = ""
) -> list[Row]:
    """A row per threshold of ``th`` not in ``seen``: not evaluated, and ``why``."""
    return [
        Row(problem, n, where, t.description, t.text, Cell(NA, title=why), NOT_EVALUATED)
        for n, t in th.items()
        if n not in seen
    ]


def acceptance_rows(src: page.Sources, thresholds: Thresholds) -> list[Row]:
    """Every target of every problem's metrics file, in report order; a problem whose metrics
    file is missing shows its thresholds (``thresholds``) as not evaluated."""
    rows: list[Row] = []
    for problem, file in ((p, f"{p}.json") for p in PROBLEMS):
        th = thresholds.get(problem) or {}
        if not src.has(file):
            rows += _absent(problem, th, set(), f"reports/metrics/{file} not found")
        else:
            rows += (fusion_rows if problem == "fusion" else target_rows)(src, th, file, problem)
    return rows


def count_line(rows: list[Row]) -> str:
    """``"n pass, n fail, n not evaluated"`` (an ablation's verdict counts as its status)."""
    n = {s: sum(r.status.split(" (")[0] == s for r in rows) for s in (PASS, FAIL, NOT_EVALUATED)}
    return f"{n[PASS]} pass, {n[FAIL]} fail, {n[NOT_EVALUATED]} not evaluated"


def elsewhere(src: page.Sources, thresholds: Thresholds) -> list[str]:
    """The fusion thresholds fusion.json does not judge (wall times: the stage's run record)."""
    block = src.get("fusion.json", "targets")
    if not isinstance(block, dict):
        return []
    return [n for n in thresholds.get("fusion") or {} if n not in block]


def acceptance_section(src: page.Sources, thresholds: Thresholds) -> Section:
    """The index's last section: the acceptance table and the count of its statuses."""
    rows = acceptance_rows(src, thresholds)
    other = elsewhere(src, thresholds)
    timed = (
        f" Judged on wall times, which differ between identical runs, so in the run record "
        f"reports/timings/evaluate_fusion.json and not here: {', '.join(other)}."
        if other
        else ""
    )
    note = (
        count_line(rows) + ". Condition: the point estimate against the threshold unless "
        "it names the interval ('whole interval': its far end) or one of its ends; 'not "
        "evaluated' where the figure, its configuration or its rows are missing (never a pass); "
        "'(ablation <name>)': a target this run does not evaluate, from that ablation "
        "experiment's own evaluation (reports/ablations/<name>.json)." + timed
    )
    title = "Every target of this run against its acceptance threshold (default-profile thresholds, test split)"
    # headline: with the headline tables in results_table.md (docs/results.md)
    table = Table(title, COLUMNS, [r.cells() for r in rows], note, ANCHOR, headline=True)
    intro = (
        "Every target's verdict, read from the metrics files' `targets` blocks; the thresholds "
        "are the acceptance config group (`conf/acceptance/default.yaml`)."
    )
    return Section(TITLE, [intro], [table])
