"""House rule: no issue numbers in code, config, docs or tests (the history stays in git). A
sentence names the property or the decision, never the ticket that asked for it."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# what the rule covers: folders (every tracked file under them) and single files
ROOTS = ("src", "pipelines", "conf", "docs", "tests", "benchmarks", "examples", ".github")
FILES = ("README.md", "params.yaml", "dvc.yaml", "Makefile")
# built from pieces so that this file does not match itself
_WORD = "iss" + "ue"
_DEFECT = "def" + "ect"
NUMBERED = re.compile(rf"\b(?:{_WORD}|{_DEFECT})s?[ \t\-]*#?\d+", re.IGNORECASE)


def _covered_files() -> list[Path]:
    """Tracked files under ROOTS plus FILES (``git ls-files``, workspace contents); outside a git
    checkout every file there except caches."""
    proc = subprocess.run(
        ["git", "ls-files", "-z", "--", *ROOTS, *FILES],
        cwd=ROOT,
        capture_output=True,
        check=False,
    )
    if proc.returncode == 0 and proc.stdout:
        names = [n for n in proc.stdout.decode().split("\0") if n]
        return [ROOT / n for n in names if (ROOT / n).is_file()]
    found = [ROOT / f for f in FILES if (ROOT / f).is_file()]
    for d in ROOTS:
        found += [p for p in (ROOT / d).rglob("*") if p.is_file() and "__pycache__" not in p.parts]
    return found


def numbered_references(text: str) -> list[str]:
    """Every ``<issue|defect> <number>`` mention in ``text`` (case-insensitive), as written."""
    return [m.group(0) for m in NUMBERED.finditer(text)]


@pytest.mark.parametrize(
    ("text", "hits"),
    [
        (f"chosen on validation ({_WORD} 31: no choice on test)", 1),
        (f"**Targets ({_WORD}s 14 and 15):**", 1),
        (f"the {_WORD}-15 target, {_WORD.title()} #7", 2),
        (f"{_WORD.upper()} 18, {_DEFECT} 13: two identical runs", 2),
        (f"{_DEFECT}s 7 and 16 of the {_WORD}", 1),
        (f"no {_WORD}s here, 31 {_DEFECT}ive pixels, tissue 5", 0),
    ],
    # ids without the texts: test ids are written to tests/durations.json, which the rule covers
    ids=["in-parentheses", "plural", "hyphen-and-hash", "upper-case", "plural-list", "none"],
)
def test_the_pattern_finds_numbered_references(text: str, hits: int) -> None:
    assert len(numbered_references(text)) == hits, numbered_references(text)


def test_no_issue_numbers_in_the_repository() -> None:
    files = _covered_files()
    assert any(p.name == "dvc.yaml" for p in files) and any(p.suffix == ".py" for p in files)
    found = []
    for path in files:
        text = path.read_bytes().decode("utf-8", errors="replace")
        for n, line in enumerate(text.splitlines(), 1):
            found += [f"{path.relative_to(ROOT)}:{n}: {hit}" for hit in numbered_references(line)]
    assert not found, "issue numbers (name the property or decision instead):\n" + "\n".join(found)
