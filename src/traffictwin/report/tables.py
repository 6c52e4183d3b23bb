"""Tables any section can use: a metrics file as a key/value table, the run's parameters, and a
problem's findings text as bullet points."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from traffictwin.report.model import NULL, Cell, Sources, Table, flatten_numbers, number_cell

FINDINGS_HEADING = "Findings of this run"


def scalar_cell(src: Sources, file: str, key: str, v: Any) -> Cell:
    """The cell of the scalar ``v`` at metrics ``file``#``key``: a number (``int`` or ``g4``) or a
    JSON ``null`` (``n/a``) with its source, any other value as text (a list's items joined)."""
    if v is None or (isinstance(v, (int, float)) and not isinstance(v, bool)):
        fmt = "int" if isinstance(v, int) else "g4"
        return number_cell(v, fmt, f"{src.path(file)}#{key}", NULL if v is None else "")
    return Cell(", ".join(map(str, v)) if isinstance(v, list) else str(v))


def generic_table(src: Sources, file: str, title: str, anchor: str = "") -> Table | None:
    """Every scalar in metrics ``file`` as a key/value table (None if the file is absent)."""
    data = src.metrics.get(file)
    if data is None:
        return None
    rows = [[Cell(key), scalar_cell(src, file, key, v)] for key, v in flatten_numbers(data)]
    return Table(title, ["key", "value"], rows, anchor=anchor)


def params_table(src: Sources) -> Table:
    rows = [[Cell(k), src.param_cell(k)] for k in sorted(src.inputs.run_params)]
    note = "The parameters the profiles override (their sizes) and every seed, from params.yaml."
    title = "Parameters of this run (scale and seeds)"
    return Table(title, ["parameter", "value"], rows, note=note, anchor="params")


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
    """Statements of a markdown findings text: bullets and paragraph lines; headings and tables
    dropped (the report's own tables show those numbers with their sources)."""
    out: list[str] = []
    for ln in text.splitlines():
        t = ln.strip()
        if not t or t.startswith(("#", "|")):
            continue
        if ln.startswith((" ", "\t")) and t[:2] not in ("- ", "* ") and out:  # a continuation
            out[-1] += " " + t
        else:
            out.append(t[2:].strip() if t[:2] in ("- ", "* ") else t)
    return out
