"""The report's page model: cells that remember their source, tables, figures, sections, and
the loaded input files (:class:`Sources`) the sections read their numbers from.

Every number in the report comes from a file: metrics JSON (``reports/metrics/*.json``, the
ablations' ``reports/ablations/*.json``), ``reports/environment.json``, the run's parameters (passed
in explicitly by the stage) or :mod:`traffictwin.paper_numbers` (the papers' reported
values, the only hand-typed numbers). Each table cell that holds a number remembers where it came
from (``Cell.src``, e.g. ``metrics/risk.json#test/mse``); the HTML carries it as ``data-src`` and
the raw value as ``data-value`` so tests can re-check every number against its file.

A missing file or key gives an ``n/a`` cell (recorded in :attr:`Sources.missing`), never an
error, so a partial pipeline still reports. Each problem (fusion, risk, ...) contributes its
part through a :class:`SectionProvider`; this module knows none of them.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from traffictwin import paper_numbers as P
from traffictwin.interval_rule import finite
from traffictwin.nested import ABSENT, lookup  # the sections import them from here too
from traffictwin.report.claims import ClaimCheck
from traffictwin.report.summary import Headline, interval

NA = "n/a"
NEVER = r"(?!)"  # a regex that matches nothing


# --------------------------------------------------------------------------- formatting
def fmt_value(value: Any, fmt: str = "g4") -> str:
    """Format one number for a table cell.

    ``fmt``: ``g4`` (4 significant digits), ``f<k>`` (k decimals), ``int`` (thousands
    separator ``,``), ``pct`` (a fraction shown as percent, 2 decimals), ``pct_raw`` (already a
    percent, 2 decimals), ``s`` (seconds → ``m:ss`` / ``h:mm:ss``), ``str`` (as is).
    NaN / None → ``n/a``.
    """
    if value is None:
        return NA
    if fmt == "str":
        return str(value)
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, str):
        return value
    v = float(value)
    if math.isnan(v):
        return NA
    if math.isinf(v):
        return "inf" if v > 0 else "-inf"
    if fmt == "g4":
        return f"{v:.4g}"
    if fmt == "int":
        return f"{int(round(v)):,}"
    if fmt == "pct":
        return f"{100.0 * v:.2f} %"
    if fmt == "pct_raw":
        return f"{v:.2f} %"
    if fmt == "s":
        t = int(round(v))
        h, rem = divmod(t, 3600)
        m, s = divmod(rem, 60)
        return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"
    m = re.fullmatch(r"f(\d)", fmt)
    if m:
        return f"{v:.{int(m.group(1))}f}"
    raise ValueError(f"fmt_value: unknown format {fmt!r}")


# --------------------------------------------------------------------------- model
@dataclass
class Cell:
    """One table cell. ``src`` names the file#key a number came from (None for labels/derived text)."""

    text: str
    src: str | None = None
    value: Any = None
    fmt: str | None = None
    title: str = ""  # tooltip (e.g. why a value is n/a)
    derived: str = ""  # how a number was derived from its sources (e.g. "95 % ... interval")


@dataclass
class Table:
    title: str
    columns: list[str]
    rows: list[list[Cell]] = field(default_factory=list)
    note: str = ""
    anchor: str = ""
    headline: bool = False  # one of the headline tables (results_table.md, the project README)


@dataclass
class Figure:
    path: str  # relative to the reports folder, e.g. "figures/fusion_kld_box.png"
    caption: str


@dataclass
class Section:
    title: str
    paragraphs: list[str] = field(default_factory=list)
    tables: list[Table] = field(default_factory=list)
    figures: list[Figure] = field(default_factory=list)
    bullet_groups: list[tuple[str, list[str]]] = field(default_factory=list)  # (heading, bullets)
    # tables[:shown] are shown open, the rest under "More tables" (None: all open)
    shown: int | None = None
    collapsed: bool = False  # the whole section in a closed <details> (appendix material)
    page: str = ""  # the page that holds it: "" the index, else reports/pages/<page>.md / .html


@dataclass
class Report:
    title: str
    intro: list[str]
    sections: list[Section]  # every section in reading order, each naming its page
    missing: list[str]


@dataclass
class Page:
    """One file of the report: the index (``name`` ``""``: ``reports/README.md`` /
    ``index.html``) or ``reports/pages/<name>.md`` / ``.html``. ``root``: the path from the page's
    folder to the reports folder (``""`` or ``"../"``), for figures and links; ``links``:
    ``(title, page name)`` of the other pages (the index's list); ``missing``: the metrics keys
    looked for and not found (on the page that lists them)."""

    name: str
    title: str
    intro: list[str]
    sections: list[Section]
    root: str = ""
    links: list[tuple[str, str]] = field(default_factory=list)
    missing: list[str] = field(default_factory=list)


@dataclass
class ReportInputs:
    """Everything the report needs, passed explicitly (the library never reads params.yaml).

    ``reports_dir``: folder with ``metrics/``, ``ablations/``, ``figures/``, ``plots/``,
    ``environment.json``; the report files are written there. ``run_params``: flattened
    ``{key: value}`` of the parameters to show (profile sizes, seeds). ``git_commit`` is not
    shown (it differs between identical reruns: the stage's run record holds it).
    ``acceptance``: the acceptance thresholds per problem (``acceptance.<problem>``,
    :func:`traffictwin.acceptance.thresholds`) of the index's last table. What a problem's
    section needs beyond these (the fusion section's pose-noise configurations) its
    :class:`SectionProvider` carries.
    """

    reports_dir: Path
    profile: str
    seed: int
    git_commit: str
    run_params: Mapping[str, Any] = field(default_factory=dict)
    banner: str = ""  # profile.banner: a smoke run's warning, first in the report and summary.json
    acceptance: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)


# --------------------------------------------------------------------------- sources
class Sources:
    """Loaded input files with number lookup that records what was missing."""

    def __init__(self, inputs: ReportInputs) -> None:
        self.inputs = inputs
        self.root = Path(inputs.reports_dir)
        self.metrics: dict[str, Any] = {}
        self.missing: list[str] = []
        self.paths: dict[str, str] = {}  # metrics file name -> its path under reports/
        # the metrics files by name; the ablation experiments' results (pipelines/ablations.py),
        # where they were collected, as "ablations/<name>"
        for folder, prefix in (("metrics", ""), ("ablations", "ablations/")):
            for p in sorted((self.root / folder).glob("*.json")):
                self.metrics[prefix + p.name] = _read_json(p)
                self.paths[prefix + p.name] = f"{folder}/{p.name}"
        if (self.root / "environment.json").exists():  # the software (the appendix shows it)
            self.metrics["environment.json"] = _read_json(self.root / "environment.json")
            self.paths["environment.json"] = "environment.json"

    def has(self, file: str) -> bool:
        return file in self.metrics

    def get(self, file: str, key: str, default: Any = None) -> Any:
        """Value at dotted ``key`` in metrics ``file`` (segments may themselves contain '/' or '.')."""
        data = self.metrics.get(file)
        return lookup(data, key, default) if data is not None else default

    def cell(self, file: str, key: str, fmt: str = "g4", *, record: bool = True) -> Cell:
        """Number cell from metrics ``file``#``key``.

        Absent key: ``n/a`` without a source, recorded in :attr:`missing`. JSON ``null`` (the
        writers' spelling of NaN, e.g. precision with no positive prediction): ``n/a`` with its source.
        """
        v = self.get(file, key, ABSENT)
        path = self.paths.get(file, f"metrics/{file}")
        if v is ABSENT or isinstance(v, (dict, list)):
            if record:
                self.missing.append(f"{path}#{key}")
            return Cell(NA, title=f"not in reports/{path}: {key}")
        if v is None:
            return Cell(
                NA,
                src=f"{path}#{key}",
                value=None,
                fmt=fmt,
                title="undefined (null in the metrics file)",
            )
        return Cell(fmt_value(v, fmt), src=f"{path}#{key}", value=v, fmt=fmt)

    def param_cell(self, key: str, fmt: str = "str") -> Cell:
        v = self.inputs.run_params.get(key)
        if v is None:
            return Cell(NA, title=f"parameter {key} not set in this run")
        return Cell(fmt_value(v, fmt), src=f"params#{key}", value=v, fmt=fmt)


def json_number(v: Any) -> float | None:
    """``v`` as a float when it is a JSON number (not a bool), else None."""
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None


def span_cell(lo: Any, hi: Any, fmt: str, derived: str, why: str = "no interval") -> Cell:
    """``[lo, hi]`` in format ``fmt``, a cell ``derived`` from the files it names; ``n/a`` (with
    ``why``) when a bound is not a finite number."""
    if finite(lo) is None or finite(hi) is None:
        return Cell(NA, title=why)
    return Cell(f"[{fmt_value(lo, fmt)}, {fmt_value(hi, fmt)}]", value=[lo, hi], derived=derived)


def interval_cell(src: Sources, file: str, key: str, bootstrap: str, fmt: str = "g4") -> Cell:
    """``[lo, hi]`` of ``<key>_ci`` (``{"lo", "hi"}`` or ``[lo, hi]``; or of ``key`` itself when it
    holds ``lo``/``hi``) in metrics ``file``, in format ``fmt``: a derived cell, "95 %
    ``bootstrap`` interval" (e.g. ``"cluster-bootstrap"``); ``n/a`` when there is no interval (or a
    NaN bound)."""
    base = key if isinstance(src.get(file, f"{key}.lo"), (int, float)) else f"{key}_ci"
    path = src.paths.get(file, f"metrics/{file}")
    lo, hi = interval(src.get(file, base)) or (None, None)
    why = f"no interval in reports/{path}: {base}"
    return span_cell(lo, hi, fmt, f"95 % {bootstrap} interval, {path}#{base}", why)


def paper_cell(table: str, key: str, fmt: str = "g4") -> Cell:
    """Cell with a paper's reported number (``paper_numbers.<table>[key]``)."""
    num = getattr(P, table)[key]
    v = num.value
    fmt = "str" if isinstance(v, str) else fmt
    return Cell(
        fmt_value(v, fmt),
        src=f"paper:{table}.{key}",
        value=v,
        fmt=fmt,
        title=f"{num.source}: {num.unit} {num.note}".strip(),
    )


def flatten_numbers(data: Any, prefix: str = "") -> list[tuple[str, Any]]:
    """``[(dotted key, scalar)]`` for every scalar leaf (numbers, bools, strings) in JSON ``data``."""
    out: list[tuple[str, Any]] = []
    if isinstance(data, dict):
        for k, v in data.items():
            out.extend(flatten_numbers(v, f"{prefix}{k}."))
    elif isinstance(data, list):
        if all(not isinstance(v, (dict, list)) for v in data) and len(data) <= 12:
            out.append((prefix[:-1], data))
        else:
            for i, v in enumerate(data):
                out.extend(flatten_numbers(v, f"{prefix}{i}."))
    else:
        out.append((prefix[:-1], data))
    return out


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not readable JSON ({exc})") from None


# --------------------------------------------------------------------------- section providers
@dataclass(frozen=True)
class DataFile:
    """A problem's data file, shown first in the report's appendix under ``title``."""

    file: str  # name in reports/metrics, e.g. "orb.json"
    title: str
    required: bool = False  # say so when it is missing (an optional file is just left out)


@dataclass(frozen=True)
class SectionProvider:
    """What one problem (fusion, risk; a cooperative twin later) contributes to the report.

    ``section(src, figures)`` builds the problem's section from the loaded files and the figures
    that were assigned to it. ``figures``: ``{file stem: caption}`` of the figures the problem's
    stages write, in the order the section shows them; ``figure_pattern``: a regex on a file stem
    that claims any other image for this problem. ``data_files``: its data files (first in the appendix).
    ``shown_files``: a regex of metrics files the section already shows in full (kept out of the
    appendix). ``replaces``: ``{stem: older stem}``, figures the report stage redraws; where the
    new one exists the older one is left out. ``name`` and ``headlines``: the problem's few headline numbers with their
    intervals (``{metrics file name: parsed JSON}`` -> :class:`~traffictwin.report.summary.Headline`
    list), written to ``reports/summary.json`` under ``name`` and shown first in the report;
    ``name`` is also its page (``reports/pages/<name>.md``). ``claims``: the paper's claims with
    this run's verdicts (same input -> :class:`~traffictwin.report.claims.ClaimCheck` list), the
    report's first table. The report iterates the providers in order; adding a problem adds a provider.
    """

    section: Callable[[Sources, list[Figure]], Section]
    figures: Mapping[str, str] = field(default_factory=dict)
    figure_pattern: str = NEVER
    data_files: Sequence[DataFile] = ()
    shown_files: str = NEVER
    replaces: Mapping[str, str] = field(default_factory=dict)  # {figure stem: stem it supersedes}
    name: str = ""
    headlines: Callable[[Mapping[str, Any]], Sequence[Headline]] | None = None
    claims: Callable[[Mapping[str, Any]], Sequence[ClaimCheck]] | None = None
