"""Copy the committed results into README.md and docs/ between markers (``make readme``):

- README.md: the report's headline table (the first of ``reports/results_table.md``) and the
  default run's wall time and longest stages (the run records ``reports/timings/*.json``);
- docs/results.md: the report's headline tables and the timing table per part of the pipeline;
- docs/benchmarks.md: the figures of ``reports/benchmarks.json``.

Tables are the report's :class:`~traffictwin.report.model.Table` (rendered by
:func:`~traffictwin.report.render.table_markdown`), sentences macros of ``templates/readme.md.j2``.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from traffictwin.io.atomic import write_text_atomic
from traffictwin.nested import lookup
from traffictwin.report.model import Cell, Table
from traffictwin.report.prose import oneline, template_macro
from traffictwin.report.render import RESULTS_TABLE, table_markdown

from ._paths import REPORTS, ROOT
from ._run_records import read_records, seconds, sessions, wall_seconds

README, RESULTS_PAGE, BENCH_PAGE = "README.md", "docs/results.md", "docs/benchmarks.md"
TEMPLATES = Path(__file__).parent / "templates"


def markers(block: str, source: str, make: str = "readme") -> tuple[str, str]:
    """The markers around a generated ``block`` written from ``source`` by ``make <make>``."""
    return (
        f"<!-- {block}:begin (generated from {source} by `make {make}`) -->",
        f"<!-- {block}:end -->",
    )


BEGIN, END = markers("results", "reports/results_table.md")
T_BEGIN, T_END = markers("timings", "reports/timings/*.json")
H_BEGIN, H_END = markers("headline", "reports/results_table.md")
TS_BEGIN, TS_END = markers("run-time", "reports/timings/*.json")
B_BEGIN, B_END = markers("benchmarks", "reports/benchmarks.json")

#: the wall time (min) `make run` (the default DAG) should take on a 2-core machine
RUN_BUDGET_MIN = 25.0
#: how many of the longest stages the README's run-time table names
LONGEST_SHOWN = 3


def _tpl(name: str) -> Any:
    """Macro or table of rows ``name`` of ``templates/readme.md.j2`` (``timing_groups``,
    ``bench_rows``, a sentence's macro)."""
    return template_macro(TEMPLATES, "readme.md.j2", name)


def _say(macro: str, *args: Any, **kwargs: Any) -> str:
    """The sentence of macro ``macro`` of ``templates/readme.md.j2``, as one line."""
    return oneline(_tpl(macro)(*args, **kwargs))


def _block(begin: str, end: str, *parts: str) -> str:
    return "\n".join([begin, *parts, end])


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
def _minutes(s: float) -> str:
    return f"{s / 60:.1f} min"


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
    return _block(T_BEGIN, T_END, table_markdown(Table("", ["what", "time"], rows)))


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
    return _block(TS_BEGIN, TS_END, table_markdown(Table("", ["what", "time"], rows)))


# ------------------------------------------------------------------ the README's headline table
def headline_block(table_md: str) -> str:
    """The README's headline table: the first table of the report's ``results_table.md`` (the
    numbers of reports/summary.json with their 95 % intervals and the strongest baseline), with
    its title and note; a sentence when the report has no table yet."""
    body = results_block(table_md).splitlines()[1:-1]
    first = "\n".join(body).split("\n\n")[:3]  # title, table, note
    return _block(H_BEGIN, H_END, "\n\n".join(first) if "|" in table_md else _say("no_results"))


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
    table = table_markdown(Table("", ["what", "figure", "machine"], rows))
    return _block(B_BEGIN, B_END, *intro, table)


# ------------------------------------------------------------------ pages
def page_blocks(read: Callable[[str], str], records: list[dict]) -> dict[str, list[str]]:
    """``{page: [block, ...]}``: every generated block of every page, from the files ``read``
    returns (paths relative to the repository root) and the run records ``records``."""
    try:
        bench = json.loads(read("reports/benchmarks.json")) or {}
    except (OSError, ValueError):  # absent or unreadable: no rows
        bench = {}
    results = read(f"reports/{RESULTS_TABLE}")
    return {
        README: [headline_block(results), run_time_block(records)],
        RESULTS_PAGE: [results_block(results), timings_block(records)],
        BENCH_PAGE: [benchmarks_block(bench)],
    }


def render(page: str, text: str, blocks: list[str]) -> str:
    """``text`` of ``page`` with each of ``blocks`` put between its markers (each block's first and
    last line, which the block replaces with everything between them)."""
    for block in blocks:
        begin, end = block.splitlines()[0], block.splitlines()[-1]
        if begin not in text or end not in text:
            raise ValueError(f"{page}: markers missing ({begin!r} … {end!r})")
        head, rest = text.split(begin, 1)
        text = head + block + rest.split(end, 1)[1]
    return text


def write_blocks(blocks: Mapping[str, list[str]]) -> None:
    """Each page's generated ``blocks`` (``{page: [block, ...]}``) into its file (:func:`render`)."""
    for page, items in blocks.items():
        path = ROOT / page
        write_text_atomic(path, render(page, path.read_text(encoding="utf-8"), items))


def main() -> None:
    records = read_records(REPORTS / "timings")
    blocks = page_blocks(lambda rel: (ROOT / rel).read_text(encoding="utf-8"), records)
    write_blocks(blocks)
    print(f"{', '.join(blocks)}: generated blocks updated from reports/")


if __name__ == "__main__":
    main()
