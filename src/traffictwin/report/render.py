"""The pipeline's report: ``reports/README.md`` (GitHub), ``reports/index.html`` (self-contained)
and ``reports/results_table.md`` (the headline tables, included by the project README).

This module only assembles: the page skeleton (intro, "This run", data section, appendix), the
figures found under ``reports/figures``, and the Markdown / HTML writers. Each problem's results
section comes from its :class:`~traffictwin.report.model.SectionProvider`
(``traffictwin.fusion.report_section``, ``traffictwin.risk.report_section``), passed in by the
caller in the order the report shows them. The page model and the sources of every number:
:mod:`traffictwin.report.model`. Anything in ``reports/metrics`` that no section shows appears in
the appendix.
"""

from __future__ import annotations

import base64
import html
import json
import re
from collections.abc import Sequence
from pathlib import Path

from traffictwin.io.atomic import write_text_atomic
from traffictwin.report.model import (
    NA,
    Cell,
    Figure,
    Report,
    ReportInputs,
    Section,
    SectionProvider,
    Sources,
    Table,
    flatten_numbers,
    fmt_value,
)
from traffictwin.report.tables import (
    environment_table,
    generic_table,
    ordered_records,
    params_table,
    pivot_table,
    timing_table,
)

# The files this module writes into the reports folder.
README = "README.md"
INDEX_HTML = "index.html"
RESULTS_TABLE = "results_table.md"
TIMINGS_README = "timings/README.md"  # beside the run records: not a DVC output
IMAGE_SUFFIXES = (".png", ".svg", ".jpg", ".jpeg", ".gif")
_MIME = {
    ".png": "image/png",
    ".svg": "image/svg+xml",
    ".jpg": "image/jpeg",
    ".jpeg": "image/jpeg",
    ".gif": "image/gif",
}


# --------------------------------------------------------------------------- figures
def collect_figures(
    reports_dir: Path, providers: Sequence[SectionProvider]
) -> tuple[list[list[Figure]], list[Figure]]:
    """Images under ``reports/figures``, one list per provider plus the unclaimed ones.

    First every provider's known figures (its ``figures`` order, with their captions), then any
    other image goes to the first provider whose ``figure_pattern`` matches its name, or to the
    unclaimed list (the appendix)."""
    out: list[list[Figure]] = [[] for _ in providers]
    other: list[Figure] = []
    fdir = Path(reports_dir) / "figures"
    if not fdir.is_dir():
        return out, other
    files = {
        p.relative_to(reports_dir).as_posix(): p
        for p in sorted(fdir.rglob("*"))
        if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
    }
    done: set[str] = set()
    for figs, prov in zip(out, providers):
        for stem, caption in prov.figures.items():
            for rel, p in files.items():
                if p.stem == stem and rel not in done:
                    figs.append(Figure(rel, f"{caption} — `{rel}`"))
                    done.add(rel)
    for rel, p in files.items():
        if rel in done:
            continue
        owner = next(
            (
                figs
                for figs, prov in zip(out, providers)
                if re.search(prov.figure_pattern, p.stem.lower())
            ),
            other,
        )
        owner.append(Figure(rel, f"`{rel}`"))
    return out, other


# --------------------------------------------------------------------------- assemble
def run_section(src: Sources) -> Section:
    """ "This run": profile, seed, commit, experiment; the parameters and machine (stage wall
    times differ between identical runs: :func:`render_timings_markdown`, outside the report)."""
    inputs = src.inputs
    run = Section("This run")
    commit = inputs.git_commit or "unknown"
    run.paragraphs.append(
        f"Profile `{inputs.profile}`, seed `{inputs.seed}`, git commit `{commit}`"
        + (" (with uncommitted changes to code or configuration)" if inputs.git_dirty else "")
        + (f", DVC experiment `{inputs.dvc_exp_name}`" if inputs.dvc_exp_name else "")
        + (
            f", pipeline run `{inputs.pipeline_run}` (MLflow tag `pipeline_run`)"
            if inputs.pipeline_run
            else ""
        )
        + "."
    )
    run.paragraphs.append(
        "The stages' wall times, training times, throughput and MLflow run ids differ between identical "
        "runs, so they are not in this report (a DVC output) but in the run records, "
        "`reports/timings/` (summary: `reports/timings/README.md`)."
    )
    run.tables.append(params_table(src))
    env_t = environment_table(src)
    if env_t:
        run.tables.append(env_t)
    return run


def data_section(src: Sources, providers: Sequence[SectionProvider]) -> Section:
    """Every provider's data files, as grids."""
    data = Section("Data and disparity statistics")
    for df in (df for prov in providers for df in prov.data_files):
        t = pivot_table(src, df.file, df.title, anchor=f"data-{Path(df.file).stem}")
        if t:
            data.tables.append(t)
        elif df.required:
            data.paragraphs.append(f"`reports/metrics/{df.file}` is missing.")
    return data


def appendix_section(
    src: Sources, providers: Sequence[SectionProvider], figures: list[Figure]
) -> Section:
    """Every metrics file no section shows in full, as a key/value table; unclaimed figures."""
    appendix = Section("Appendix — every metrics file")
    shown = {df.file for prov in providers for df in prov.data_files}
    for file in src.metrics:
        if file in shown or any(re.fullmatch(prov.shown_files, file) for prov in providers):
            continue
        t = generic_table(src, file, f"reports/metrics/{file}", anchor=f"m-{Path(file).stem}")
        if t:
            appendix.tables.append(t)
    appendix.figures = figures
    return appendix


def build_report(inputs: ReportInputs, providers: Sequence[SectionProvider]) -> Report:
    """Assemble the report model from the files under ``inputs.reports_dir``: "This run", one
    section per provider (in order), the data section and the appendix."""
    src = Sources(inputs)
    figures, other = collect_figures(src.root, providers)
    intro = [
        "Generated by the DVC stage `report` from the metrics and figures of one pipeline run; "
        "do not edit by hand. Every number below comes from a file: `reports/metrics/*.json`, "
        "`reports/environment.json`, the run's `params.yaml`, or — for the "
        "papers' values — `src/traffictwin/report/paper_numbers.py` (with the section they are printed in).",
        "**The data differs from the papers'.** Both papers used commercial simulators (VTD, GTA V) at full "
        "scale; this run uses traffictwin's own simulator (synthetic road templates, ray-cast lidar, rendered "
        f"stereo camera) at the `{inputs.profile}` profile's scale. Compare trends and rankings, not absolute values.",
    ]
    sections = [
        run_section(src),
        *(prov.section(src, figs) for prov, figs in zip(providers, figures)),
        data_section(src, providers),
        appendix_section(src, providers, other),
    ]
    return Report("traffictwin — results report", intro, sections, sorted(set(src.missing)))


def results_tables(report: Report) -> list[Table]:
    """The headline tables (for results_table.md / the project README)."""
    return [t for s in report.sections for t in s.tables if t.headline]


# --------------------------------------------------------------------------- markdown
def _md_cell(c: Cell) -> str:
    return c.text.replace("|", "\\|").replace("\n", " ")


def table_markdown(t: Table) -> str:
    lines = [
        f"**{t.title}**",
        "",
        "| " + " | ".join(x.replace("|", "\\|") for x in t.columns) + " |",
        "|" + "|".join(" --- " for _ in t.columns) + "|",
    ]
    for row in t.rows:
        lines.append("| " + " | ".join(_md_cell(c) for c in row) + " |")
    if t.note:
        lines += ["", f"<sub>{t.note}</sub>"]
    return "\n".join(lines)


def render_markdown(report: Report) -> str:
    out = [f"# {report.title}", ""]
    for p in report.intro:
        out += [p, ""]
    out += [
        "Contents: " + " · ".join(f"[{s.title}](#{_slug(s.title)})" for s in report.sections),
        "",
    ]
    for s in report.sections:
        out += [f"## {s.title}", ""]
        for p in s.paragraphs:
            out += [p, ""]
        for head, bullets in s.bullet_groups:
            out += [f"### {head}", ""] + [f"- {b}" for b in bullets] + [""]
        for t in s.tables:
            out += [table_markdown(t), ""]
        for f in s.figures:
            out += [f"![{_alt(f.caption)}]({f.path})", "", f"*{f.caption}*", ""]
    if report.missing:
        out += [
            "## Missing values",
            "",
            "These metrics were looked for and not found (shown as `n/a`):",
            "",
        ]
        out += [f"- `{m}`" for m in report.missing] + [""]
    return "\n".join(out).rstrip() + "\n"


def render_timings_markdown(inputs: ReportInputs) -> str:
    """``reports/timings/README.md``: the stages' run records (``reports/timings/*.json``) as one
    page — the wall-time table in DAG order (``inputs.stage_order``), then every other number of
    each record (training seconds, ms per pair or frame, MLflow run ids, ...)."""
    src = Sources(inputs)
    out = [
        "# Run records",
        "",
        "<!-- generated by the DVC stage `report` from reports/timings/*.json; not a DVC output -->",
        "",
        "What differs between two identical runs of a stage — its wall time, training time and "
        "throughput, the MLflow run id and model URI of a training run — is written by the stage "
        "to its run record `reports/timings/<stage>.json` (`@` as `-`), never into a DVC output, so "
        "an identical `dvc repro -f` leaves `dvc.lock` unchanged. The records are committed with "
        "the results; the promotion gate reads the MLflow run ids from them.",
        "",
        table_markdown(timing_table(src, inputs.stage_order)),
        "",
    ]
    for stage, _name, d in ordered_records(src, inputs.stage_order):
        rest = [(k, v) for k, v in flatten_numbers(d) if k not in ("stage", "seconds")]
        if not rest:
            continue
        out += [f"## {stage}", ""]
        out += [f"- `{k}`: {fmt_value(v, 'g4') if isinstance(v, float) else v}" for k, v in rest]
        out.append("")
    return "\n".join(out).rstrip() + "\n"


def render_results_markdown(report: Report, link: str = README) -> str:
    out = ["<!-- generated by the DVC stage `report`; do not edit -->", ""]
    for t in results_tables(report):
        out += [table_markdown(t), ""]
    out.append(f"Full report: [{link}]({link}).")
    return "\n".join(out) + "\n"


def _slug(title: str) -> str:
    s = re.sub(r"[^\w\- ]", "", title.lower()).strip()
    return re.sub(r"\s", "-", s)


def _alt(caption: str) -> str:
    return re.sub(r"[`\[\]]", "", caption)


# --------------------------------------------------------------------------- html
CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;max-width:1200px;margin:2em auto;padding:0 1em;color:#222}
table{border-collapse:collapse;margin:.5em 0 1.5em 0;font-size:.9em}
th,td{border:1px solid #ccc;padding:.25em .6em;text-align:right}
th{background:#f3f3f3} td:first-child,th:first-child{text-align:left}
td.na{color:#999} caption{text-align:left;font-weight:600;margin-bottom:.3em}
figure{margin:1em 0} figure img{max-width:100%;border:1px solid #eee}
figcaption{font-size:.9em;color:#555} p.note{font-size:.85em;color:#555;margin-top:-1em}
code{background:#f5f5f5;padding:0 .2em}
"""


def _inline(text: str) -> str:
    s = html.escape(text, quote=False)
    s = re.sub(r"`([^`]+)`", r"<code>\1</code>", s)
    s = re.sub(r"\*\*([^*]+)\*\*", r"<strong>\1</strong>", s)
    s = re.sub(
        r"\[([^\]]+)\]\(([^)\s]+)\)",
        lambda m: f'<a href="{html.escape(m.group(2))}">{m.group(1)}</a>',
        s,
    )
    return s


def table_html(t: Table) -> str:
    attrs = f' id="{html.escape(t.anchor)}"' if t.anchor else ""
    out = [
        f"<table{attrs}>",
        f"<caption>{_inline(t.title)}</caption>",
        "<thead><tr>" + "".join(f"<th>{html.escape(c)}</th>" for c in t.columns) + "</tr></thead>",
        "<tbody>",
    ]
    for row in t.rows:
        tds = []
        for c in row:
            a = []
            if c.src:
                a.append(f'data-src="{html.escape(c.src)}"')
                a.append(f'data-value="{html.escape(json.dumps(c.value))}"')
                a.append(f'data-fmt="{html.escape(c.fmt or "")}"')
            if c.derived:
                a.append(f'data-derived="{html.escape(c.derived)}"')
                a.append(f'data-value="{html.escape(json.dumps(c.value))}"')
            if c.title:
                a.append(f'title="{html.escape(c.title)}"')
            if c.text == NA:
                a.append('class="na"')
            tds.append(f"<td{' ' + ' '.join(a) if a else ''}>{_inline(c.text)}</td>")
        out.append("<tr>" + "".join(tds) + "</tr>")
    out.append("</tbody></table>")
    if t.note:
        out.append(f'<p class="note">{_inline(t.note)}</p>')
    return "\n".join(out)


def figure_html(f: Figure, reports_dir: Path, embed: bool = True) -> str:
    p = Path(reports_dir) / f.path
    if embed:
        data = base64.b64encode(p.read_bytes()).decode("ascii")
        srcattr = f"data:{_MIME.get(p.suffix.lower(), 'application/octet-stream')};base64,{data}"
    else:
        srcattr = html.escape(f.path)
    return (
        f'<figure><img src="{srcattr}" alt="{html.escape(_alt(f.caption))}" data-file="{html.escape(f.path)}"/>'
        f"<figcaption>{_inline(f.caption)}</figcaption></figure>"
    )


def render_html(report: Report, reports_dir: Path, embed: bool = True) -> str:
    """Self-contained HTML (figures embedded as base64 unless ``embed=False``)."""
    out = [
        "<!DOCTYPE html>",
        '<html lang="en">',
        "<head>",
        '<meta charset="utf-8"/>',
        f"<title>{html.escape(report.title)}</title>",
        f"<style>{CSS}</style>",
        "</head>",
        "<body>",
        f"<h1>{html.escape(report.title)}</h1>",
    ]
    out += [f"<p>{_inline(p)}</p>" for p in report.intro]
    out.append(
        "<nav><ul>"
        + "".join(
            f'<li><a href="#{_slug(s.title)}">{html.escape(s.title)}</a></li>'
            for s in report.sections
        )
        + "</ul></nav>"
    )
    for s in report.sections:
        out.append(f'<section id="{_slug(s.title)}"><h2>{html.escape(s.title)}</h2>')
        out += [f"<p>{_inline(p)}</p>" for p in s.paragraphs]
        for head, bullets in s.bullet_groups:
            out.append(f"<h3>{html.escape(head)}</h3>")
            out.append("<ul>" + "".join(f"<li>{_inline(b)}</li>" for b in bullets) + "</ul>")
        out += [table_html(t) for t in s.tables]
        out += [figure_html(f, reports_dir, embed) for f in s.figures]
        out.append("</section>")
    if report.missing:
        out.append(
            '<section id="missing"><h2>Missing values</h2><ul>'
            + "".join(f"<li><code>{html.escape(m)}</code></li>" for m in report.missing)
            + "</ul></section>"
        )
    out += ["</body>", "</html>"]
    return "\n".join(out) + "\n"


# --------------------------------------------------------------------------- write
def write_report(inputs: ReportInputs, providers: Sequence[SectionProvider]) -> Report:
    """Build the report and write README.md, index.html and results_table.md into
    ``inputs.reports_dir`` (atomically)."""
    root = Path(inputs.reports_dir)
    report = build_report(inputs, providers)
    md = render_markdown(report)
    page = render_html(report, root, embed=True)
    res = render_results_markdown(report)
    write_text_atomic(root / README, md)
    write_text_atomic(root / INDEX_HTML, page)
    write_text_atomic(root / RESULTS_TABLE, res)
    return report


def write_timings_readme(inputs: ReportInputs) -> Path:
    """Write :func:`render_timings_markdown` to ``<reports_dir>/timings/README.md`` (atomically);
    returns the path."""
    path = Path(inputs.reports_dir) / TIMINGS_README
    write_text_atomic(path, render_timings_markdown(inputs))
    return path
