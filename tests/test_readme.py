"""README.md shows the committed report's numbers and the two setup commands."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipelines.readme_results import BEGIN, END, render, results_block

ROOT = Path(__file__).resolve().parents[1]


def test_readme_results_match_the_committed_report() -> None:
    readme = (ROOT / "README.md").read_text()
    table = (ROOT / "reports" / "results_table.md").read_text()
    assert results_block(table) in readme, (
        "README.md results are stale: run `make readme` after `make run`"
    )


def test_readme_names_the_two_commands() -> None:
    readme = (ROOT / "README.md").read_text()
    assert "make run" in readme and "make test" in readme


def test_render_replaces_only_the_block() -> None:
    readme = f"intro\n{BEGIN}\nold\n{END}\noutro\n"
    out = render(
        readme, "<!-- generated -->\n| a |\n| --- |\n| 1 |\nFull report: [README.md](README.md).\n"
    )
    assert out == f"intro\n{BEGIN}\n| a |\n| --- |\n| 1 |\n{END}\noutro\n"
    with pytest.raises(ValueError, match="markers missing"):
        render("no markers", "x")
