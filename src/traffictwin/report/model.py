"""The report's page model: cells that remember their source, tables, figures, sections, and
the loaded input files (:class:`Sources`) the sections read their numbers from.

Every number comes from a file: metrics JSON (``reports/metrics/*.json``, the ablations'
``reports/ablations/*.json``), ``reports/environment.json``, the run's parameters or
:mod:`traffictwin.paper_numbers` (the papers' values, the only hand-typed numbers). A number
cell remembers where it came from (``Cell.src``, e.g. ``metrics/risk.json#test/mse``), so tests
re-check every number the pages show against its file. A missing file or key gives an ``n/a`` cell (recorded in :attr:`Sources.missing`),
never an error. Each problem contributes a :class:`SectionProvider`; this module knows none.
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
NULL = "undefined (null in the metrics file)"  # the title of a JSON null's n/a cell

_FORMATS: dict[str, Callable[[float], str]] = {
    "g4": lambda v: f"{v:.4g}",
    "int": lambda v: f"{int(round(v)):,}",
    "pct": lambda v: f"{100.0 * v:.2f} %",
    "pct_raw": lambda v: f"{v:.2f} %",
}


def fmt_value(value: Any, fmt: str = "g4") -> str:
    """One number as a table cell's text. ``fmt``: ``g4`` (4 significant digits), ``f<k>`` (k
    decimals), ``int`` (thousands separator ``,``), ``pct`` (a fraction as percent, 2 decimals),
    ``pct_raw`` (already a percent), ``s`` (seconds as ``m:ss`` / ``h:mm:ss``), ``str`` (as is).
    NaN / None: ``n/a``."""
    if value is None:
        return NA
    if fmt == "str" or isinstance(value, str):
        return str(value)
    if isinstance(value, bool):
        return str(value).lower()
    v = float(value)
    if math.isnan(v):
        return NA
    if math.isinf(v):
        return "inf" if v > 0 else "-inf"
    if fmt == "s":
        m, s = divmod(int(round(v)), 60)
        h, m = divmod(m, 60)
        return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"
    if m := re.fullmatch(r"f(\d)", fmt):
        return f"{v:.{int(m.group(1))}f}"
    if fmt not in _FORMATS:
        raise ValueError(f"fmt_value: unknown format {fmt!r}")
    return _FORMATS[fmt](v)


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


def number_cell(value: Any, fmt: str, src: str, title: str = "") -> Cell:
    """The cell of ``value`` read from ``src`` (``file#key``), in format ``fmt``."""
    return Cell(fmt_value(value, fmt), src=src, value=value, fmt=fmt, title=title)


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
    """One file of the report: the index (``name`` ``""``) or ``reports/pages/<name>.md`` /
    ``.html``. ``root``: the path from the page's folder to the reports folder (``""`` or
    ``"../"``); ``links``: ``(title, page name)`` of the pages (the index's list); ``missing``: the
    metrics keys looked for and not found (on the page that lists them)."""

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
    ``environment.json``, where the report is written. ``run_params``: flattened ``{key: value}``
    of the parameters to show. ``git_commit`` is not shown (it differs between identical reruns).
    ``acceptance``: the acceptance thresholds per problem (``acceptance.<problem>``) of the
    index's last table.
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
        # the metrics files by name, the ablation experiments' results as "ablations/<name>",
        # the software (the appendix shows it)
        env = self.root / "environment.json"
        files = [
            p for d in ("metrics", "ablations") for p in sorted((self.root / d).glob("*.json"))
        ]
        for p in [*files, *([env] if env.exists() else [])]:
            rel = p.relative_to(self.root).as_posix()
            name = rel.removeprefix("metrics/")
            self.metrics[name], self.paths[name] = _read_json(p), rel

    def has(self, file: str) -> bool:
        return file in self.metrics

    def path(self, file: str) -> str:
        """Metrics ``file``'s path under reports/."""
        return self.paths.get(file, f"metrics/{file}")

    def get(self, file: str, key: str, default: Any = None) -> Any:
        """Value at dotted ``key`` in metrics ``file`` (segments may themselves contain '/' or '.')."""
        data = self.metrics.get(file)
        return lookup(data, key, default) if data is not None else default

    def cell(self, file: str, key: str, fmt: str = "g4", *, record: bool = True) -> Cell:
        """Number cell from metrics ``file``#``key``: ``n/a`` without a source where the key is
        absent (recorded in :attr:`missing`), ``n/a`` with its source for a JSON ``null`` (the
        writers' NaN, e.g. precision with no positive prediction)."""
        v = self.get(file, key, ABSENT)
        if v is ABSENT or isinstance(v, (dict, list)):
            if record:
                self.missing.append(f"{self.path(file)}#{key}")
            return Cell(NA, title=f"not in reports/{self.path(file)}: {key}")
        return number_cell(v, fmt, f"{self.path(file)}#{key}", NULL if v is None else "")

    def param_cell(self, key: str, fmt: str = "str") -> Cell:
        v = self.inputs.run_params.get(key)
        if v is None:
            return Cell(NA, title=f"parameter {key} not set in this run")
        return number_cell(v, fmt, f"params#{key}")


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
    holds ``lo``/``hi``) in metrics ``file``: a derived cell, "95 % ``bootstrap`` interval" (e.g.
    ``"cluster-bootstrap"``); ``n/a`` when there is no interval (or a NaN bound)."""
    base = key if isinstance(src.get(file, f"{key}.lo"), (int, float)) else f"{key}_ci"
    lo, hi = interval(src.get(file, base)) or (None, None)
    why = f"no interval in reports/{src.path(file)}: {base}"
    return span_cell(lo, hi, fmt, f"95 % {bootstrap} interval, {src.path(file)}#{base}", why)


def paper_cell(table: str, key: str, fmt: str = "g4") -> Cell:
    """Cell with a paper's reported number (``paper_numbers.<table>[key]``)."""
    num = getattr(P, table)[key]
    fmt = "str" if isinstance(num.value, str) else fmt
    title = f"{num.source}: {num.unit} {num.note}".strip()
    return number_cell(num.value, fmt, f"paper:{table}.{key}", title)


def flatten_numbers(data: Any, prefix: str = "") -> list[tuple[str, Any]]:
    """``[(dotted key, scalar)]`` for every scalar leaf (numbers, bools, strings) in JSON ``data``;
    a list of at most 12 scalars is one leaf."""
    if isinstance(data, dict):
        items: Any = data.items()
    elif isinstance(data, list) and (
        len(data) > 12 or any(isinstance(v, (dict, list)) for v in data)
    ):
        items = enumerate(data)
    else:
        return [(prefix[:-1], data)]
    return [kv for k, v in items for kv in flatten_numbers(v, f"{prefix}{k}.")]


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
    """What one problem contributes to the report; the report iterates the providers in order.

    ``section(src, figures)``: the problem's section from the loaded files and its figures.
    ``figures``: ``{file stem: caption}`` of its stages' figures, in the order shown;
    ``figure_pattern``: a regex on a file stem that claims any other image. ``data_files``: shown
    first in the appendix. ``shown_files``: a regex of metrics files the section shows in full
    (kept out of the appendix). ``name``: its page (``reports/pages/<name>.md``) and its
    key in ``reports/summary.json``; ``headlines``: its headline numbers (``{metrics file:
    parsed JSON}`` -> :class:`~traffictwin.report.summary.Headline` list); ``claims``: the paper's
    claims with this run's verdicts (-> :class:`~traffictwin.report.claims.ClaimCheck` list).
    """

    section: Callable[[Sources, list[Figure]], Section]
    figures: Mapping[str, str] = field(default_factory=dict)
    figure_pattern: str = NEVER
    data_files: Sequence[DataFile] = ()
    shown_files: str = NEVER
    name: str = ""
    headlines: Callable[[Mapping[str, Any]], Sequence[Headline]] | None = None
    claims: Callable[[Mapping[str, Any]], Sequence[ClaimCheck]] | None = None
