"""The pipeline's report: the index ``reports/README.md`` / ``reports/index.html`` (does this run
reproduce the papers, the headline numbers, the acceptance table, links to the pages), one page
per section under ``reports/pages/`` (``<name>.md`` and ``<name>.html``, figures as files) and
``reports/results_table.md`` (the headline tables, included by the project README).

This module only assembles (the intro, the verdict and headline tables, "This run", the appendix
of every metrics file no section shows, the figures under ``reports/figures``) and writes (one
Jinja template renders every page's Markdown, markdown-it its HTML from that Markdown). Each
problem's section, headline numbers and paper claims come from its
:class:`~traffictwin.report.model.SectionProvider`, in the caller's order; a provider's page is
its ``name``.
"""

from __future__ import annotations

import html
import re
from collections.abc import Mapping, Sequence
from dataclasses import astuple, replace
from functools import cache
from pathlib import Path
from typing import Any

from traffictwin.io.atomic import write_json_atomic, write_text_atomic
from traffictwin.report.acceptance import ANCHOR as ACCEPTANCE_ANCHOR
from traffictwin.report.acceptance import acceptance_section
from traffictwin.report.claims import VERDICTS, ClaimCheck
from traffictwin.report.model import (
    NA,
    Cell,
    Figure,
    Page,
    Report,
    ReportInputs,
    Section,
    SectionProvider,
    Sources,
    Table,
    number_cell,
    span_cell,
)
from traffictwin.report.prose import template_environment
from traffictwin.report.summary import Headline, summary_json
from traffictwin.report.tables import generic_table, params_table

# The files this module writes into the reports folder.
README = "README.md"
INDEX_HTML = "index.html"
PAGES = "pages"  # reports/pages/<name>.md and .html: one page per section
RESULTS_TABLE = "results_table.md"
STYLE = "style.css"  # the HTML pages' one style sheet (:data:`CSS`), linked from each page
SUMMARY = "summary.json"  # the headline numbers: the only DVC metrics file
TEMPLATES = Path(__file__).resolve().parent / "templates"
FIGURE_DIRS = ("figures",)  # the figures plot_data draws
IMAGE_SUFFIXES = (".png", ".svg", ".jpg", ".jpeg", ".gif")


# --------------------------------------------------------------------------- figures
def collect_figures(
    reports_dir: Path, providers: Sequence[SectionProvider]
) -> tuple[list[list[Figure]], list[Figure]]:
    """The images of :data:`FIGURE_DIRS`, one list per provider (its known ``figures`` first, in
    order, with their captions; then the images its ``figure_pattern`` claims) and the unclaimed
    ones (the appendix's)."""
    out: list[list[Figure]] = [[] for _ in providers]
    other: list[Figure] = []
    files = {
        p.relative_to(reports_dir).as_posix(): p
        for d in FIGURE_DIRS
        if (Path(reports_dir) / d).is_dir()
        for p in sorted((Path(reports_dir) / d).rglob("*"))
        if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
    }
    done: set[str] = set()
    for figs, prov in zip(out, providers):
        for stem, caption in prov.figures.items():
            for rel, p in files.items():
                if p.stem == stem and rel not in done:
                    figs.append(Figure(rel, f"{caption} — `{rel}`"))
                    done.add(rel)
    for rel, p in ((rel, p) for rel, p in files.items() if rel not in done):
        claims = (
            f for f, prov in zip(out, providers) if re.search(prov.figure_pattern, p.stem.lower())
        )
        next(claims, other).append(Figure(rel, f"`{rel}`"))
    return out, other


# --------------------------------------------------------------------------- assemble
def run_section(src: Sources) -> Section:
    """ "This run": the parameters (the software is in the appendix)."""
    note = (
        "The stages' wall times, training times, throughput and MLflow run ids differ between identical "
        "runs, so they are not in this report (a DVC output) but in the run records, "
        "`reports/timings/<stage>.json`."
    )
    return Section("This run: parameters, machine", [note], [params_table(src)], collapsed=True)


def appendix_section(
    src: Sources, providers: Sequence[SectionProvider], figures: list[Figure]
) -> Section:
    """Every metrics file no section shows in full, as a key/value table (the providers' data
    files first, under their titles; a required one that is missing said so); unclaimed figures."""
    appendix = Section("Appendix — every metrics file", collapsed=True)
    data = {df.file: df for prov in providers for df in prov.data_files}
    appendix.paragraphs += [
        f"`reports/metrics/{f}` is missing."
        for f, df in data.items()
        if df.required and not src.has(f)
    ]
    for file in [*(f for f in data if src.has(f)), *(f for f in src.metrics if f not in data)]:
        if any(re.fullmatch(prov.shown_files, file) for prov in providers):
            continue
        if file.startswith("ablations/"):  # an experiment's own results: linked, not dumped
            appendix.paragraphs.append(
                f"`reports/{src.paths.get(file, file)}`: results of the ablation experiment "
                f"{src.get(file, 'experiment', '?')} (commit {str(src.get(file, 'commit', '?'))[:8]}); "
                "the sections above show what they compare."
            )
            continue
        title = data[file].title if file in data else f"reports/{src.paths[file]}"
        appendix.tables.append(generic_table(src, file, title, anchor=f"m-{Path(file).stem}"))
    appendix.figures = figures
    return appendix


def collect_headlines(
    metrics: Mapping[str, Any], providers: Sequence[SectionProvider]
) -> dict[str, list[Headline]]:
    """``{provider name: its headline numbers}`` from the loaded metrics files, in provider order."""
    return {
        prov.name or f"section{i}": list(prov.headlines(metrics))
        for i, prov in enumerate(providers)
        if prov.headlines is not None
    }


HEADLINE_NOTE = (
    "Intervals: the sections' 95 % bootstrap intervals (fusion: scenarios resampled; risk and "
    "twin: driving sequences resampled). Strongest baseline: the best method without the shipped "
    "model on the same quantity and frames (fusion: fusion rules without a network or learned "
    "registration; risk: rules and constant predictors, not the oracle on exact disparity; twin: "
    "the other maps). Details on the report's pages."
)


def headline_section(headlines: Mapping[str, Sequence[Headline]]) -> Section:
    """Every provider's headline numbers (those of ``reports/summary.json``) as one table, each
    beside its strongest baseline; a value cell's source is its key in summary.json."""
    columns = ["problem", "quantity", "where", "value", "95 % CI"]
    columns += ["strongest baseline", "its value", "95 % CI"]
    title = "Headline results (reports/summary.json, the DVC metrics file)"
    # headline: the first table of results_table.md, the project README's
    t = Table(title, columns, anchor="headline", note=HEADLINE_NOTE, headline=True)
    for problem, items in headlines.items():
        for h in items:
            path, b = f"{problem}.{h.key}", h.baseline
            ci = f"95 % bootstrap interval, {SUMMARY}#{path}_lo / {path}_hi"
            base = [Cell("—"), Cell("—"), Cell("—")]
            if b is not None:
                bci, why = f"95 % bootstrap interval of {b.src}", f"no interval beside {b.src}"
                base = [Cell(b.name), number_cell(b.value, h.fmt, b.src)]
                base.append(span_cell(b.lo, b.hi, h.fmt, bci, why))
            labels = map(Cell, (problem, h.quantity, h.where))
            value = number_cell(h.value, h.fmt, f"{SUMMARY}#{path}")
            t.rows.append([*labels, value, span_cell(h.lo, h.hi, h.fmt, ci), *base])
    if t.rows:
        return Section("Headline results", tables=[t])
    return Section(
        "Headline results", ["No headline numbers yet (the evaluation stages have not run)."]
    )


VERDICTS_TITLE = "Does this run reproduce the papers?"


def claims_section(claims: Sequence[ClaimCheck]) -> Section:
    """The verdict table: one row per claim of a paper (its text and where the paper makes it),
    this run's numbers with their 95 % intervals and the verdict computed from them
    (:mod:`traffictwin.report.claims`), then a count of the verdicts."""
    if not claims:
        return Section(
            VERDICTS_TITLE, ["No claim could be checked yet (the evaluation stages have not run)."]
        )
    counts = {v: sum(c.verdict == v for c in claims) for v in VERDICTS}
    count = (
        f"{len(claims)} claims of the papers: "
        + ", ".join(f"{n} {v}" for v, n in counts.items())
        + ". Reproduced: each 95 % interval lies on the side the paper claims (a difference is a "
        "finding only when its interval excludes 0), or reaches the number the paper prints; "
        "exceeded: our whole interval lies beyond the paper's number on the better side (above "
        "its accuracy, below its error); not comparable: no interval in this run's metrics."
    )
    t = Table(
        "Paper claims against this run",
        ["paper", "claim", "where (paper)", "this run (95 % CI)", "verdict"],
        anchor="verdicts",
        note="Our data is the project's own simulator at this profile's scale, not the papers': "
        "the verdicts compare trends and rankings. Details on each paper's page.",
    )
    t.rows = [list(map(Cell, astuple(c))) for c in claims]  # paper, claim, where, measured, verdict
    return Section(VERDICTS_TITLE, [count], [t])


def _headline_first(sec: Section) -> Section:
    """Headline tables first (their order kept), the others under "More tables"."""
    if sec.shown is None and sec.tables:
        sec.tables = sorted(sec.tables, key=lambda t: not t.headline)
        sec.shown = max(1, sum(t.headline for t in sec.tables))
    return sec


def build_report(
    inputs: ReportInputs,
    providers: Sequence[SectionProvider],
    headlines: Mapping[str, Sequence[Headline]] | None = None,
) -> Report:
    """The report model from the files under ``inputs.reports_dir``: the index (the verdicts, the
    headline numbers (``headlines``, default: :func:`collect_headlines`), the acceptance table),
    one page per provider (headline tables first), then "This run" and the appendix."""
    src = Sources(inputs)
    if headlines is None:
        headlines = collect_headlines(src.metrics, providers)
    figures, other = collect_figures(src.root, providers)
    intro = [  # the commit, experiment and pipeline run differ between identical reruns: not here
        *([f"**{inputs.banner.strip('() ')}.**"] if inputs.banner else []),
        f"Profile `{inputs.profile}`, seed `{inputs.seed}`. The git commit, DVC experiment and "
        "pipeline run (MLflow tag `pipeline_run`) of this rendering are in its run record "
        "`reports/timings/report.json`.",
        "**The data differs from the papers'.** Both papers used commercial simulators (VTD, GTA V) at full "
        "scale; this run uses traffictwin's own simulator (synthetic road templates, ray-cast lidar, rendered "
        f"stereo camera) at the `{inputs.profile}` profile's scale. Compare trends and rankings, not absolute values.",
    ]
    head = headline_section(headlines)
    head.paragraphs.insert(
        0,
        "Generated by the DVC stage `report` from the metrics and figures of one pipeline run; "
        "do not edit by hand. Every number in the report comes from a file: `reports/summary.json`, "
        "`reports/metrics/*.json`, `reports/environment.json`, the run's "
        "`params.yaml`, or — for the papers' values — `src/traffictwin/paper_numbers.py` (with the "
        "section they are printed in).",
    )
    problems = [_headline_first(prov.section(src, figs)) for prov, figs in zip(providers, figures)]
    sections = [
        claims_section(
            [c for p in providers if p.claims is not None for c in p.claims(src.metrics)]
        ),
        head,
        acceptance_section(src, inputs.acceptance),  # the index's last section
        *(  # a problem's page: its provider's name, else its title's slug
            replace(sec, page=prov.name or _slug(sec.title))
            for prov, sec in zip(providers, problems)
        ),
        replace(run_section(src), page="run"),
        replace(appendix_section(src, providers, other), page="appendix"),
    ]
    return Report("traffictwin — results report", intro, sections, sorted(set(src.missing)))


def report_pages(report: Report) -> list[Page]:
    """The report split into its files: the index (the sections without a page, then the list of
    pages) and one page per page name, in reading order; the missing values on the last page."""
    names = list(dict.fromkeys(s.page for s in report.sections if s.page))
    pages = {n: [s for s in report.sections if s.page == n] for n in ["", *names]}
    links = [(pages[n][0].title, n) for n in names]
    out = [Page("", report.title, report.intro, pages[""], links=links)]
    out += [Page(n, pages[n][0].title, [], pages[n], root="../", links=links) for n in names]
    out[-1].missing = list(report.missing)
    return out


def results_tables(report: Report) -> list[Table]:
    """The headline tables (for results_table.md / the project README), the acceptance table
    last (as on the index)."""
    tables = [t for s in report.sections for t in s.tables if t.headline]
    return sorted(tables, key=lambda t: t.anchor == ACCEPTANCE_ANCHOR)


# --------------------------------------------------------------------------- markdown
def table_markdown(t: Table) -> str:
    """``t`` as a Markdown table: its title in bold (none when empty), the header, the rows, the
    note."""

    def row(cells: Any) -> str:
        return "| " + " | ".join(x.replace("|", "\\|") for x in cells) + " |"

    lines = [f"**{t.title}**", ""] if t.title else []
    lines += [row(t.columns), "|" + "|".join(" --- " for _ in t.columns) + "|"]
    lines += [row(c.text.replace("\n", " ") for c in r) for r in t.rows]
    if t.note:
        lines += ["", f"<sub>{t.note}</sub>"]
    return "\n".join(lines)


def _environment() -> Any:
    """The Jinja2 environment of the report templates (``templates/`` next to this module)."""
    env = template_environment(TEMPLATES)
    env.filters.update(alt=_alt, table_md=table_markdown)
    return env


def _tidy(text: str) -> str:
    """At most one blank line in a row; one newline at the end."""
    return re.sub(r"\n{3,}", "\n\n", text).strip() + "\n"


def render_pages(report: Report, html_pages: bool = False) -> dict[str, str]:
    """``{file relative to reports/: text}`` of every page: Markdown (template ``page.md.j2``: the
    index ``README.md`` and ``pages/<name>.md``) or HTML (``index.html`` and
    ``pages/<name>.html``: each page's Markdown rendered by :func:`html_page`)."""
    tpl = _environment().get_template("page.md.j2")
    out = {}
    for p in report_pages(report):
        md = _tidy(tpl.render(report=report, page=p))
        if not html_pages:
            out[f"{PAGES}/{p.name}.md" if p.name else README] = md
            continue
        title = f"{report.title}: {p.title}" if p.name else report.title
        out[f"{PAGES}/{p.name}.html" if p.name else INDEX_HTML] = html_page(md, title, p.root)
    return out


def render_results_markdown(report: Report, link: str = README) -> str:
    """``reports/results_table.md`` (template ``results_table.md.j2``): the headline tables."""
    tpl = _environment().get_template("results_table.md.j2")
    return _tidy(tpl.render(tables=results_tables(report), link=link))


def _slug(title: str) -> str:
    s = re.sub(r"[^\w\- ]", "", title.lower()).strip()
    return re.sub(r"\s", "-", s)


def _alt(caption: str) -> str:
    return re.sub(r"[`\[\]]", "", caption)


# --------------------------------------------------------------------------- html
#: the HTML pages' style sheet, written once to ``reports/style.css`` (:data:`STYLE`)
CSS = """body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;max-width:1200px;margin:2em auto;padding:0 1em;color:#222}
table{border-collapse:collapse;margin:0 0 .5em 0;font-size:.9em}
th,td{border:1px solid #ccc;padding:.25em .6em;text-align:left;vertical-align:top}
th{background:#f3f3f3} td.num{text-align:right;white-space:nowrap}
td.na{color:#999;text-align:right}
p>sub{display:block;font-size:.95em;color:#555;margin-bottom:1.5em}
img{max-width:100%;border:1px solid #eee} code{background:#f5f5f5;padding:0 .2em}
details>summary{cursor:pointer} details{margin:.5em 0 1.5em 0}
"""

#: an HTML page around its rendered Markdown ``body``, linking the style sheet
HTML_PAGE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8"/>
<meta name="viewport" content="width=device-width, initial-scale=1"/>
<title>{title}</title>
<link rel="stylesheet" href="{root}{style}"/>
</head>
<body>
{body}</body>
</html>
"""


def html_page(markdown: str, title: str, root: str) -> str:
    """A page's Markdown as HTML (markdown-it: CommonMark with tables; raw HTML such as
    ``<details>`` passes through), with :func:`_html_tokens`' changes, linking the style sheet
    from ``root`` (the path from the page's folder to the reports folder)."""
    body = _markdown_it().render(markdown)
    return HTML_PAGE.format(title=html.escape(title), root=root, style=STYLE, body=body)


@cache
def _markdown_it() -> Any:
    from markdown_it import MarkdownIt

    md = MarkdownIt("commonmark", {"xhtmlOut": True}).enable("table")
    md.core.ruler.push("report_html", _html_tokens)
    return md


def _html_tokens(state: Any) -> None:
    """Headings get the ids GitHub gives them (their slugs: the anchors the pages link), links to
    the Markdown pages point at the HTML ones, table cells that show a number (or n/a) get the
    style sheet's class ``num`` (``na``): right-aligned; text stays left-aligned. Inline HTML other
    than ``<sub>`` (the tables' notes) is text."""
    tokens = state.tokens
    for tok, nxt in zip(tokens, tokens[1:]):
        if tok.type == "heading_open":
            tok.attrSet("id", _slug(nxt.content))
        elif tok.type == "td_open" and (cls := cell_class(nxt.content)):
            tok.attrSet("class", cls)
        for child in nxt.children or ():
            if child.type == "link_open":
                child.attrSet("href", _html_href(str(child.attrGet("href"))))
            elif child.type == "html_inline" and not re.match(r"</?sub>$", child.content):
                child.type = "text"  # a placeholder such as <name> in prose: shown as written


def cell_class(text: str) -> str | None:
    """The class of a table cell showing ``text``: ``na`` for n/a, ``num`` for a number, an
    interval or a percentage, None for text."""
    if text == NA:
        return "na"
    return "num" if _NUMBER.match(text) else None


def _html_href(href: str) -> str:
    """A relative link to a Markdown page as the HTML report's (``../README.md#a`` -> ``../index.html#a``)."""
    path, sep, anchor = href.partition("#")
    if "://" in path or not path.endswith(".md"):
        return href
    html_path = path[: -len(README)] + INDEX_HTML if path.endswith(README) else path[:-3] + ".html"
    return html_path + sep + anchor


#: a cell that shows a number: a value (with a short unit), a signed difference, a percentage or
#: an interval "[lo, hi]"
_NUMBER = re.compile(
    r"^\[?[-+−]?\.?\d[\d.,eE+\-−% ]*(?:[a-zA-Zµ°/]{1,4})?(?:, [-+−]?\.?\d[\d.eE+\-−% ]*(?:[a-zA-Zµ°/]{1,4})?\])?$"
)


# --------------------------------------------------------------------------- write
def write_report(inputs: ReportInputs, providers: Sequence[SectionProvider]) -> Report:
    """Write ``summary.json``, the index README.md and index.html, the pages (a page left from an
    earlier rendering is removed), ``style.css`` and results_table.md into ``inputs.reports_dir``
    (each atomically)."""
    root = Path(inputs.reports_dir)
    headlines = collect_headlines(Sources(inputs).metrics, providers)
    write_json_atomic(root / SUMMARY, summary_json(headlines, inputs.banner))
    report = build_report(inputs, providers, headlines)
    files = {**render_pages(report), **render_pages(report, html_pages=True), STYLE: CSS}
    files[RESULTS_TABLE] = render_results_markdown(report)
    for rel, text in files.items():
        write_text_atomic(root / rel, text)
    pages = root / PAGES
    for old in sorted(pages.glob("*")) if pages.is_dir() else ():
        if old.is_file() and f"{PAGES}/{old.name}" not in files:
            old.unlink()
    return report
