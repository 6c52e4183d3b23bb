"""Copy the generated results table (reports/results_table.md) into README.md between markers.

``make readme`` runs it after ``make run``; ``tests/test_readme.py`` fails when README.md shows
other numbers than the committed report, so the two cannot drift apart silently.
"""

from __future__ import annotations

from traffictwin.io.atomic import write_text_atomic
from traffictwin.report.render import RESULTS_TABLE

from ._paths import REPORTS, ROOT

BEGIN = "<!-- results:begin (generated from reports/results_table.md by `make readme`) -->"
END = "<!-- results:end -->"


def results_block(table_md: str) -> str:
    """The README block for ``table_md``: the table without its generated-file comment or link line."""
    lines = [
        ln
        for ln in table_md.splitlines()
        if not ln.startswith("<!--") and not ln.startswith("Full report:")
    ]
    body = "\n".join(lines).strip().replace("](README.md)", "](reports/README.md)")
    return f"{BEGIN}\n{body}\n{END}"


def render(readme: str, table_md: str) -> str:
    """``readme`` with the text between the markers replaced by :func:`results_block`."""
    if BEGIN not in readme or END not in readme:
        raise ValueError(f"README.md: markers missing ({BEGIN!r} … {END!r})")
    head, rest = readme.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    return head + results_block(table_md) + tail


def main() -> None:
    readme = ROOT / "README.md"
    new = render(readme.read_text(), (REPORTS / RESULTS_TABLE).read_text())
    write_text_atomic(readme, new)
    print("README.md: results block updated from reports/results_table.md")


if __name__ == "__main__":
    main()
