"""Copy the committed results into README.md and docs/ between markers (``make readme``).

What goes where, each block from files that ``make run`` / ``make bench`` write:

- README.md, *Headline results*: three small tables (fusion, risk, twin) with their 95 % intervals,
  from ``reports/metrics/{fusion,risk,twin}.json`` and the configurations of ``params.yaml``;
- README.md, *How long it takes*: the default run's wall time and stage time, from the run records
  ``reports/timings/*.json``;
- docs/results.md: the report's headline tables (``reports/results_table.md``) and the timing table
  per part of the pipeline (the run records);
- docs/benchmarks.md: the figures of ``reports/benchmarks.json``.

Tables are the report's :class:`~traffictwin.report.model.Table` (rendered by its
:func:`~traffictwin.report.render.table_markdown`), sentences macros of ``templates/readme.md.j2``.
``tests/test_readme.py`` fails when a page shows other numbers than the committed files.
``make docs`` also runs :mod:`pipelines.docs_reference` (CLI reference, test counts).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from traffictwin.io.atomic import write_text_atomic
from traffictwin.nested import lookup
from traffictwin.report.model import NA, Cell, Table, fmt_value
from traffictwin.report.prose import oneline, template_macro
from traffictwin.report.render import RESULTS_TABLE, table_markdown

from ._paths import REPORTS, ROOT
from ._run_records import read_records, seconds, sessions, wall_seconds

README, RESULTS_PAGE, BENCH_PAGE = "README.md", "docs/results.md", "docs/benchmarks.md"
TEMPLATES = Path(__file__).parent / "templates"


def _markers(block: str, source: str) -> tuple[str, str]:
    """The begin and end markers of a generated ``block`` written from ``source``."""
    return (
        f"<!-- {block}:begin (generated from {source} by `make readme`) -->",
        f"<!-- {block}:end -->",
    )


BEGIN, END = _markers("results", "reports/results_table.md")
T_BEGIN, T_END = _markers("timings", "reports/timings/*.json")
H_BEGIN, H_END = _markers("headline", "reports/metrics/{fusion,risk,twin}.json")
TS_BEGIN, TS_END = _markers("run-time", "reports/timings/*.json")
B_BEGIN, B_END = _markers("benchmarks", "reports/benchmarks.json")

#: the wall time (min) `make run` (the default DAG) should take on a 2-core machine
RUN_BUDGET_MIN = 25.0
#: how many of the longest stages the README's run-time table names
LONGEST_SHOWN = 3


def _tpl(name: str) -> Any:
    """Macro or table of rows ``name`` of ``templates/readme.md.j2`` (which rows the tables show,
    their labels and sentences: ``timing_groups``, ``fusion_methods``, ``twin_targets``, ...)."""
    return template_macro(TEMPLATES, "readme.md.j2", name)


def _say(macro: str, *args: Any, **kwargs: Any) -> str:
    """The sentence of macro ``macro`` of ``templates/readme.md.j2``, as one line."""
    return oneline(_tpl(macro)(*args, **kwargs))


def _block(begin: str, end: str, *parts: str) -> str:
    return "\n".join([begin, *parts, end])


def _table(columns: list[str], rows: list[list[Cell]]) -> str:
    return table_markdown(Table("", columns, rows))


# ------------------------------------------------------------------ the results page's block
def results_block(table_md: str, reports_link: str = "../reports/README.md") -> str:
    """The results page's block for ``table_md``: the table without its generated-file comment or
    link line; links to the report point at ``reports_link`` (relative to docs/), links to its
    pages (``pages/<name>.md``) at the same pages beside it."""
    lines = [ln for ln in table_md.splitlines() if not ln.startswith(("<!--", "Full report:"))]
    pages = f"]({reports_link.rsplit('/', 1)[0]}/pages/"
    body = "\n".join(lines).strip().replace("](README.md)", f"]({reports_link})")
    return _block(BEGIN, END, body.replace("](pages/", pages))


# ------------------------------------------------------------------ timings
def _minutes(seconds: float) -> str:
    return f"{seconds / 60:.1f} min"


def _time_rows(records: list[dict]) -> list[list[Cell]]:
    """The run's wall time (:func:`wall_seconds`; with the machines, their load and the stages run
    apart; no row without timed records) and the sum of the stages' own times."""
    rows = []
    parts = sessions(records)
    if parts:
        ms = [r["machine"] for s in parts for r in s if "machine" in r]
        main = max(range(len(parts)), key=lambda i: len(parts[i]))  # the others ran apart
        what = _say(
            "wall",
            apart=[r["stage"] for i, s in enumerate(parts) if i != main for r in s],
            machines=sorted({(m["cpu"], m["cpu_count"]) for m in ms}),
            loads=[m["load_start"][0] for m in ms if m.get("load_start")],
        )
        rows.append([Cell(what), Cell(f"**{_minutes(wall_seconds(records) or 0.0)}**")])
    total = _minutes(sum(map(seconds, records)))
    return [*rows, [Cell(_say("own_time", n=len(records))), Cell(total)]]


def timings_block(records: list[dict]) -> str:
    """The results page's timing table from the run records of one ``dvc repro``: the wall time,
    the sum of the stages' times, the machine and its load, and the stage time per part of the
    pipeline."""
    rows = _time_rows(records)
    for what, stages in _tpl("timing_groups"):
        names = {s.split("@")[0] for s in stages.split()}
        secs = [seconds(r) for r in records if str(r.get("stage", "")).split("@")[0] in names]
        if secs:
            label = ", ".join(f"`{s}`" for s in stages.split())
            rows.append([Cell(f"— {what}: {label}"), Cell(_minutes(sum(secs)))])
    return _block(T_BEGIN, T_END, _table(["what", "time"], rows))


def run_time_block(records: list[dict]) -> str:
    """The README's timing table: the default run's wall time, the stages' own time, the
    :data:`LONGEST_SHOWN` longest stages, and the run against :data:`RUN_BUDGET_MIN`."""
    rows = _time_rows(records)
    longest = sorted((r for r in records if seconds(r) > 0), key=lambda r: -seconds(r))
    if longest := longest[:LONGEST_SHOWN]:
        what = _say("longest", stages=[(r["stage"], seconds(r) / 60) for r in longest])
        rows.append([Cell(what), Cell(_minutes(sum(map(seconds, longest))))])
    span = wall_seconds(records)
    if span is not None:
        budget = _say("budget", budget=RUN_BUDGET_MIN, over=span / 60 - RUN_BUDGET_MIN)
        rows.append([Cell("the budget of `make run` on a 2-core machine"), Cell(budget)])
    return _block(TS_BEGIN, TS_END, _table(["what", "time"], rows))


# ------------------------------------------------------------------ the README's headline tables
def _ci_cell(entry: Mapping, key: str, fmt: str, ci_key: str = "") -> Cell:
    """``value [lo, hi]`` of ``entry[key]`` and its interval ``entry[ci_key or key + "_ci"]``
    (``{"lo", "hi"}`` or ``[lo, hi]``; without one the value alone); ``n/a`` without a value."""
    value, ci = entry.get(key), entry.get(ci_key or f"{key}_ci")
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        return Cell("n/a")
    text = fmt_value(value, fmt)
    ci = [ci.get("lo"), ci.get("hi")] if isinstance(ci, Mapping) else ci
    if isinstance(ci, (list, tuple)) and len(ci) == 2:
        text += f" [{fmt_value(ci[0], fmt)}, {fmt_value(ci[1], fmt)}]"
    return Cell(text, value=value, fmt=fmt)


def fusion_table(fusion: Mapping, configurations: Mapping) -> Table | None:
    """KLD(b) per configuration for the baseline, classical registration, the network and the best
    learned combination (``fusion.json``: ``test.<cfg>.<method>.kld_fou_mean`` and its CI)."""
    test = lookup(fusion, "test")
    if not isinstance(test, Mapping) or not test:
        return None
    rows, methods = [], _tpl("fusion_methods")
    for cfg in sorted(test):
        label = _say("configuration", cfg, lookup(configurations, cfg) or {})
        kld = [lookup(test, f"{cfg}.{m}") or {} for m in methods]
        rows.append([Cell(label), *(_ci_cell(k, "kld_fou_mean", "g4") for k in kld)])
    title = _say("fusion", n=lookup(fusion, "n_pairs.per_config"))
    return Table(title, ["config (r, α)", *methods.values()], rows)


def risk_table(risk: Mapping) -> Table | None:
    """ROC-AUC and balanced accuracy at the first THW threshold for the shipped predictor, the SGM
    corridor rule, the DAVE-2 headline network (seed mean) and the speed-only baseline."""
    ts = lookup(risk, "thresholds_s")
    if not isinstance(ts, list) or not ts:
        return None
    main = lookup(risk, "main_variant") or "headline"
    n_seeds = lookup(risk, f"groups.{main}.n_seeds")
    rows = []
    for label, key in (
        (_say("shipped", lookup(risk, "selection.shipped_from")), "models.shipped"),
        ("baseline: corridor rule on SGM disparity", "baselines.geometric_sgm"),
        (_say("network", main, n_seeds), f"groups.{main}" if n_seeds else f"models.{main}"),
        ("baseline: speed only", "baselines.speed_only"),
    ):
        row = lookup(risk, f"{key}.at_{float(ts[0]):g}s")
        if isinstance(row, Mapping):
            scores = [_ci_cell(row, m, "f3") for m in ("roc_auc", "balanced_accuracy")]
            rows.append([Cell(label), *scores])
    n = lookup(risk, "n_frames.test"), lookup(risk, "n_sequences.test")
    return Table(
        _say("risk", float(ts[0]), *n), ["predictor", "ROC-AUC", "balanced accuracy"], rows
    )


def _condition_text(acceptance: Mapping, name: str) -> str:
    """The acceptance condition of the twin's target ``name`` (``acceptance.twin.<name>`` of
    params.yaml, e.g. ``">= 0.9"``); ``n/a`` when the config has none or it is not valid."""
    from traffictwin.acceptance import threshold
    from traffictwin.config import ConfigError

    node = acceptance.get(name)
    try:
        return threshold(node, name, f"acceptance.twin.{name}").text if node else NA
    except ConfigError:
        return NA


def twin_table(twin: Mapping, acceptance: Mapping | None = None) -> Table | None:
    """A few of the twin's targets (``twin.json``: ``targets``): value, interval, the condition
    (``acceptance``: params.yaml's ``acceptance.twin``) and whether it is met."""
    targets = lookup(twin, "targets")
    if not isinstance(targets, Mapping):
        return None
    rows = []
    for key, (fmt, quantity) in _tpl("twin_targets").items():
        t = targets.get(key)
        if isinstance(t, Mapping) and "value" in t:
            met = "yes" if t.get("met") is True else "no" if t.get("met") is False else "n/a"
            cond = Cell(_condition_text(acceptance or {}, key))
            rows.append([Cell(quantity), _ci_cell(t, "value", fmt, "ci"), cond, Cell(met)])
    if not rows:
        return None
    title = _say("twin", targets.get("method"), targets.get("configuration"))
    return Table(title, ["quantity", "value [95 % CI]", "threshold", "met"], rows)


def headline_block(
    fusion: Mapping,
    risk: Mapping,
    twin: Mapping,
    configurations: Mapping | None = None,
    acceptance: Mapping | None = None,
) -> str:
    """The README's three small headline tables between :data:`H_BEGIN` / :data:`H_END`
    (``acceptance``: params.yaml's ``acceptance.twin``, the twin targets' conditions)."""
    tables = [
        fusion_table(fusion, configurations or {}),
        risk_table(risk),
        twin_table(twin, acceptance),
    ]
    body = "\n\n".join(table_markdown(t) for t in tables if t) or _say("no_results")
    return _block(H_BEGIN, H_END, body, "", _say("headline_note"))


# ------------------------------------------------------------------ benchmarks
def _bench_rows(bench: Mapping) -> list[list[Cell]]:
    """``[what, figure, machine]`` per benchmark figure in ``bench`` (``benchmarks`` of
    reports/benchmarks.json); a benchmark that did not run, or lacks a key, gives no row."""
    import jinja2

    rows = []
    for name, macro in _tpl("bench_rows"):
        if not isinstance(b := bench.get(name), Mapping):
            continue
        try:
            what, figure = (x.strip() for x in _say(f"bench_{macro}", b).split("||"))
        except (KeyError, TypeError, ValueError, jinja2.UndefinedError):
            continue
        rows.append([Cell(f"{what} (`{name}`)"), Cell(figure), Cell(_say("machine", b))])
    return rows


def benchmarks_block(results: Mapping) -> str:
    """docs/benchmarks.md's table of ``reports/benchmarks.json`` (``make bench``)."""
    env, bench = lookup(results, "environment"), lookup(results, "benchmarks")
    rows = _bench_rows(bench if isinstance(bench, Mapping) else {})
    intro = [_say("bench_intro", env), ""] if isinstance(env, Mapping) and env else []
    return _block(B_BEGIN, B_END, *intro, _table(["what", "figure", "machine"], rows))


# ------------------------------------------------------------------ pages
def replace_block(text: str, begin: str, end: str, block: str, name: str = "README.md") -> str:
    """``text`` with everything from ``begin`` to ``end`` (the markers included) replaced by
    ``block`` (which starts with ``begin`` and ends with ``end``)."""
    if begin not in text or end not in text:
        raise ValueError(f"{name}: markers missing ({begin!r} … {end!r})")
    head, rest = text.split(begin, 1)
    _, tail = rest.split(end, 1)
    return head + block + tail


def page_blocks(read: Callable[[str], str], records: list[dict]) -> dict[str, list[str]]:
    """``{page: [block, ...]}``: every generated block of every page, from the files ``read``
    returns (paths relative to the repository root) and the run records ``records``."""
    import yaml

    def js(rel: str) -> Any:  # the file's JSON (YAML), {} when absent or unreadable
        try:
            return (yaml.safe_load if rel.endswith(".yaml") else json.loads)(read(rel)) or {}
        except (OSError, ValueError):
            return {}

    fusion, risk, twin = (js(f"reports/metrics/{f}.json") for f in ("fusion", "risk", "twin"))
    params = js("params.yaml")
    configurations = lookup(params, "configurations") or {}
    acceptance = lookup(params, "acceptance.twin") or {}
    return {
        README: [
            headline_block(fusion, risk, twin, configurations, acceptance),
            run_time_block(records),
        ],
        RESULTS_PAGE: [results_block(read(f"reports/{RESULTS_TABLE}")), timings_block(records)],
        BENCH_PAGE: [benchmarks_block(js("reports/benchmarks.json"))],
    }


def render(page: str, text: str, blocks: list[str]) -> str:
    """``text`` of ``page`` with each of ``blocks`` put between its markers (each block's first and
    last line)."""
    for block in blocks:
        lines = block.splitlines()
        text = replace_block(text, lines[0], lines[-1], block, page)
    return text


def main() -> None:
    records = read_records(REPORTS / "timings")
    blocks = page_blocks(lambda rel: (ROOT / rel).read_text(encoding="utf-8"), records)
    for page, items in blocks.items():
        path = ROOT / page
        write_text_atomic(path, render(page, path.read_text(encoding="utf-8"), items))
    print(f"{', '.join(blocks)}: generated blocks updated from reports/ and params.yaml")


if __name__ == "__main__":
    main()
