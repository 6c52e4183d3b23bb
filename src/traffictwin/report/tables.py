"""Tables any section can use: metrics files as key/value tables or side by side, the run's
parameters, and a problem's findings text as bullet points."""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from typing import Any

from traffictwin.report.model import (
    ABSENT,
    Cell,
    Sources,
    Table,
    flatten_numbers,
    fmt_value,
)

FINDINGS_HEADING = "Findings of this run"


def scalar_cell(src: Sources, file: str, key: str, v: Any) -> Cell:
    """The cell of the scalar ``v`` at metrics ``file``#``key``: a number (``int`` or ``g4``) or a
    JSON ``null`` (``n/a``) with its source, any other value as text (a list's items joined by
    commas)."""
    if v is None or (isinstance(v, (int, float)) and not isinstance(v, bool)):
        fmt = "int" if isinstance(v, int) else "g4"
        why = "undefined (null in the metrics file)" if v is None else ""
        path = src.paths.get(file, f"metrics/{file}")
        return Cell(fmt_value(v, fmt), src=f"{path}#{key}", value=v, fmt=fmt, title=why)
    return Cell(", ".join(map(str, v)) if isinstance(v, list) else fmt_value(v, "str"))


def files_table(src: Sources, pattern: str, title: str, anchor: str) -> Table | None:
    """Metrics files matching ``pattern`` (a regex with one group naming the column) side by side:
    rows = keys (union, first file's order), columns = files."""
    files = [(m.group(1), f) for f in src.metrics if (m := re.fullmatch(pattern, f))]
    if not files:
        return None
    keys: list[str] = []
    for _, f in files:
        keys += [k for k, v in flatten_numbers(src.metrics[f]) if k not in keys]
    t = Table(title, ["key", *[name for name, _ in files]], anchor=anchor)
    for k in keys:
        row = [Cell(k)]
        for _, f in files:
            v = src.get(f, k, ABSENT)
            row.append(Cell("") if v is ABSENT else scalar_cell(src, f, k, v))
        t.rows.append(row)
    return t


def generic_table(src: Sources, file: str, title: str, anchor: str = "") -> Table | None:
    """Every scalar in metrics ``file`` as a key/value table (None if the file is absent)."""
    data = src.metrics.get(file)
    if data is None:
        return None
    t = Table(title, ["key", "value"], anchor=anchor)
    t.rows = [[Cell(key), scalar_cell(src, file, key, v)] for key, v in flatten_numbers(data)]
    return t


def params_table(src: Sources) -> Table:
    t = Table(
        "Parameters of this run (scale and seeds)",
        ["parameter", "value"],
        anchor="params",
        note="The parameters the profiles override (their sizes) and every seed, from params.yaml.",
    )
    for k in sorted(src.inputs.run_params):
        t.rows.append([Cell(k), src.param_cell(k)])
    return t


# --------------------------------------------------------------------------- findings
def findings_group(
    src: Sources, file: str, findings: Callable[[Mapping[str, Any]], str]
) -> tuple[str, list[str]]:
    """``(heading, bullets)``: ``findings`` (a problem's markdown findings of metrics ``file``) as
    bullet points, or a note that the file is missing."""
    data = src.metrics.get(file)
    if data is None:
        return FINDINGS_HEADING, [f"(no {file}: findings need the evaluation metrics)"]
    return FINDINGS_HEADING, markdown_bullets(findings(data))


def markdown_bullets(text: str) -> list[str]:
    """Statements of a markdown findings text: bullets and paragraph lines; headings and tables dropped
    (the report's own tables show those numbers with their sources)."""
    out: list[str] = []
    for ln in text.splitlines():
        t = ln.strip()
        if not t or t.startswith("#") or t.startswith("|"):
            continue
        if t[:2] in ("- ", "* "):
            out.append(t[2:].strip())
        elif ln.startswith((" ", "\t")) and out:  # continuation of a bullet
            out[-1] += " " + t
        else:
            out.append(t)
    return out
