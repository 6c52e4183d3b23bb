"""Documentation inside the repository: design notes in docs/design.md (every citation resolves),
working relative links and anchors on every page, the generated reference pages (CLI, test
counts) equal to what their generator writes now, LICENSE and CITATION.cff."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from pipelines import docs_reference as D

ROOT = Path(__file__).resolve().parents[1]
DESIGN = ROOT / "docs" / "design.md"
#: every Markdown page of the documentation: the README, every page in docs/, the examples' page
PAGES = (
    "README.md",
    *sorted(f"docs/{p.name}" for p in (ROOT / "docs").glob("*.md")),
    "examples/README.md",
)
_LINK = re.compile(r"\]\(([^)\s]+)\)")
#: a section cited by name: DESIGN.md "Risk metric" (older spelling) or docs/design.md "Risk metric"
_CITED = re.compile(r"(?:DESIGN\.md|docs/design\.md)\s+[\"']([A-Z][^\"'\n]+)[\"']")


def sections(text: str) -> list[str]:
    """Names a Markdown page defines: its headings and its bold run-in titles (``- **Grid.**``)."""
    heads = re.findall(r"^#+\s+(.+?)\s*$", text, re.M)
    bold = re.findall(r"^\s*(?:- )?\*\*([^*]+?)\.?\*\*", text, re.M)
    return heads + bold


def test_sections_finds_headings_and_bold_titles() -> None:
    md = "# T\n## Decisions already taken\n- **Grid.** 256\n- **SGM.** x\ntext **not.**\n"
    assert sections(md) == ["T", "Decisions already taken", "Grid", "SGM"]


def test_every_cited_design_section_exists() -> None:
    names = sections(DESIGN.read_text())
    cited = set()
    for folder in ("src", "pipelines", "tests", "conf"):
        for path in (ROOT / folder).rglob("*"):
            if path.suffix in (".py", ".yaml", ".md") and path.is_file():
                cited |= set(_CITED.findall(path.read_text(encoding="utf-8")))
    assert "Risk metric" in cited  # the scan finds the citations at all
    missing = sorted(c for c in cited if not any(n.startswith(c) for n in names))
    assert not missing, f"cited but not a section of docs/design.md: {missing}"


@pytest.mark.parametrize("page", PAGES)
def test_design_notes_are_cited_at_their_place_in_the_repository(page: str) -> None:
    text = (ROOT / page).read_text()
    assert "DESIGN.md" not in text, f"{page} cites DESIGN.md, which is docs/design.md"


def test_pages_cover_every_docs_page() -> None:
    assert {"README.md", "docs/design.md", "docs/cli.md", "examples/README.md"} <= set(PAGES)
    assert len(PAGES) == len(list((ROOT / "docs").glob("*.md"))) + 2


_FENCED = re.compile(r"^```.*?^```[ \t]*$", re.M | re.S)


def anchors(text: str) -> set[str]:
    """The anchors GitHub gives a Markdown page's headings: lower case, punctuation other than
    ``-`` and ``_`` dropped, spaces as ``-``; a repeated heading gets ``-1``, ``-2``, ..."""
    seen: dict[str, int] = {}
    out = set()
    for head in re.findall(r"^#+\s+(.+?)\s*#*$", _FENCED.sub("", text), re.M):
        slug = re.sub(r"[^\w\- ]", "", head.strip().lower()).replace(" ", "-")
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        out.add(slug if n == 0 else f"{slug}-{n}")
    return out


def test_anchors_follow_github() -> None:
    md = "# The `traffictwin` command\n## How to add …\n## Cooperative twin — risk from N vehicles' maps\n## A\n## A\n```\n# not a heading\n```\n"
    assert anchors(md) == {
        "the-traffictwin-command",
        "how-to-add-",
        "cooperative-twin--risk-from-n-vehicles-maps",
        "a",
        "a-1",
    }


@pytest.mark.parametrize("page", PAGES)
def test_relative_links_resolve(page: str) -> None:
    """Every relative link names an existing file, and its ``#anchor`` (on a Markdown page) a
    heading of that page."""
    path = ROOT / page
    broken = []
    for target in _LINK.findall(_FENCED.sub("", path.read_text())):
        if re.match(r"[a-z]+:", target):
            continue
        file, _, anchor = target.partition("#")
        dest = (path.parent / file) if file else path
        if not dest.exists():
            broken.append(target)
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest.read_text()):
            broken.append(target)
    assert not broken, f"{page}: links to missing files or headings {broken}"


# ------------------------------------------------------------------ generated reference pages
def test_cli_reference_is_the_parsers_help() -> None:
    """docs/cli.md's reference is what `make docs` generates from the parser now."""
    page = (ROOT / D.CLI_PAGE).read_text(encoding="utf-8")
    assert D.CLI_BEGIN in page and D.CLI_END in page
    assert D.cli_block() in page, "docs/cli.md: the CLI reference is stale: run `make docs`"


def test_cli_reference_covers_every_command_and_ignores_the_terminal(monkeypatch) -> None:
    from traffictwin.cli import build_parser

    names = [name for name, _ in D.commands(build_parser())]
    assert names[:2] == ["traffictwin", "traffictwin fuse"] and "traffictwin runs compare" in names
    block = D.cli_block()
    for name in names:
        assert f"### `{name}`" in block
    monkeypatch.setenv("COLUMNS", "40")
    assert D.cli_block() == block
    assert max(len(ln) for ln in block.splitlines() if not ln.startswith("<!--")) <= D.WIDTH


def test_parse_collected_reads_both_summaries() -> None:
    assert D.parse_collected("a\n\n960/1091 tests collected (131 deselected) in 13.93s\n") == (
        960,
        1091,
    )
    assert D.parse_collected("1 test collected in 0.1s") == (1, 1)
    with pytest.raises(ValueError, match="no count"):
        D.parse_collected("ERROR: file not found")
    block = D.tests_block(960, 1091)
    assert block.startswith(D.TESTS_BEGIN) and block.endswith(D.TESTS_END)
    assert "**1,091** tests" in block and "**960** of them" in block and "131 left out" in block


def test_make_test_fast_uses_the_documented_marker_expression() -> None:
    assert f'-m "{D.FAST}"' in (ROOT / "Makefile").read_text()


def _counts_of_this_run(config: pytest.Config, items: list[pytest.Item]) -> tuple[int, int] | None:
    """``(fast, total)`` of this session's own collection when it is the whole suite (``make
    test``: every test collected, nothing deselected), read off each test's markers as `make
    test-fast`'s expression :data:`D.FAST` selects them; ``None`` for a partial run."""
    from conftest import whole_suite

    if not whole_suite(config) or config.option.deselect or config.getoption("lf", False):
        return None
    marks = re.findall(r"not (\w+)", D.FAST)
    assert " and ".join(f"not {m}" for m in marks) == D.FAST, f"not `not A and not B ...`: {D.FAST}"
    fast = sum(not any(item.get_closest_marker(m) for m in marks) for item in items)
    return fast, len(items)


@pytest.mark.integration  # a pytest collection in a subprocess (~20 s) where the run is partial
def test_test_counts_match_a_fresh_collection(request: pytest.FixtureRequest) -> None:
    """docs/testing.md says how many tests `make test` and `make test-fast` run: the counts of
    this run's collection when it is the whole suite, else of a fresh `pytest --collect-only`
    (one collection; nothing runs)."""
    counts = _counts_of_this_run(request.config, request.session.items)
    fast, total = counts if counts is not None else D.collect_counts()
    page = (ROOT / D.TESTING_PAGE).read_text(encoding="utf-8")
    assert D.tests_block(fast, total) in page, (
        f"docs/testing.md: the test counts are stale ({total} tests, {fast} fast): run `make docs`"
    )


def test_license_is_mit_for_the_contributors() -> None:
    text = (ROOT / "LICENSE").read_text()
    assert text.startswith("MIT License") and "traffictwin contributors" in text
    assert "WITHOUT WARRANTY OF ANY KIND" in text


def test_citation_cff_cites_the_software_and_both_papers() -> None:
    cff = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    assert cff["cff-version"] == "1.2.0" and cff["type"] == "software"
    assert cff["message"] and cff["title"] and cff["authors"] and cff["license"] == "MIT"
    refs = {r["title"]: r for r in cff["references"]}
    assert set(refs) == {
        "Combined Registration and Fusion of Evidential Occupancy Grid Maps for Live Digital Twins of Traffic",
        "Dynamic Risk Assessment for Vehicles of Higher Automation Levels by Deep Learning",
    }
    for ref in refs.values():
        assert ref["type"] and ref["authors"]
        assert all(a["family-names"] and a["given-names"] for a in ref["authors"])
    first = [a["family-names"] for r in refs.values() for a in r["authors"][:1]]
    assert first == ["van Kempen", "Feth"]
    assert not re.search(r"^\s*doi:", (ROOT / "CITATION.cff").read_text(), re.M)  # none invented
