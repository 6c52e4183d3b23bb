"""Documentation inside the repository: design notes in docs/design.md (every citation resolves),
working relative links, LICENSE and CITATION.cff."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
DESIGN = ROOT / "docs" / "design.md"
PAGES = ("README.md", "docs/design.md", "examples/README.md")
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


@pytest.mark.parametrize("page", PAGES)
def test_relative_links_resolve(page: str) -> None:
    path = ROOT / page
    broken = []
    for target in _LINK.findall(path.read_text()):
        if re.match(r"[a-z]+:", target) or target.startswith("#"):
            continue
        if not (path.parent / target.split("#")[0]).exists():
            broken.append(target)
    assert not broken, f"{page}: links to missing files {broken}"


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
