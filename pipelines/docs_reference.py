"""Generated reference pages in docs/ (``make docs``; ``python -m pipelines.docs_reference``),
each between BEGIN / END markers, so that ``tests/test_docs.py`` fails when they drift:

- docs/cli.md: the help of every ``traffictwin`` command, from the argparse parser
  (:func:`traffictwin.cli.build_parser`), at a fixed width (the text depends on no terminal);
- docs/testing.md: how many tests ``make test`` and ``make test-fast`` run, from a fresh
  ``pytest --collect-only``.
"""

from __future__ import annotations

import argparse
import functools
import re
import subprocess
import sys
from collections.abc import Iterator

from ._paths import ROOT
from .readme_results import markers, write_blocks

CLI_PAGE = "docs/cli.md"
TESTING_PAGE = "docs/testing.md"
CLI_BEGIN, CLI_END = markers("cli", "traffictwin.cli.build_parser()", "docs")
TESTS_BEGIN, TESTS_END = markers("tests", "`pytest --collect-only`", "docs")
#: the help text's width in characters (argparse would otherwise follow $COLUMNS / the terminal)
WIDTH = 100
#: the marker expression of `make test-fast` (Makefile); tests/test_docs.py checks they agree
FAST = "not slow and not integration and not long"


# ------------------------------------------------------------------ CLI reference
def commands(
    parser: argparse.ArgumentParser, name: str = "traffictwin"
) -> Iterator[tuple[str, argparse.ArgumentParser]]:
    """``(command line, parser)`` of ``parser`` and of every sub-command below it, depth first, in
    the order they were added."""
    yield name, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub_name, sub in action.choices.items():
                yield from commands(sub, f"{name} {sub_name}")


def help_text(parser: argparse.ArgumentParser, width: int = WIDTH) -> str:
    """``parser.format_help()`` at ``width`` columns (the parser is left as it was)."""
    cls = parser.formatter_class
    parser.formatter_class = functools.partial(cls, width=width)
    try:
        return parser.format_help()
    finally:
        parser.formatter_class = cls


def cli_block() -> str:
    """docs/cli.md's generated block: one section per command with its help."""
    from traffictwin.cli import build_parser

    parts = [CLI_BEGIN]
    for name, parser in commands(build_parser()):
        parts += [f"### `{name}`", "", "```text", help_text(parser).rstrip("\n"), "```", ""]
    return "\n".join([*parts[:-1], CLI_END])


# ------------------------------------------------------------------ test counts
_COLLECTED = re.compile(r"^(\d+)(?:/(\d+))? tests? collected", re.M)


def parse_collected(output: str) -> tuple[int, int]:
    """``(selected, total)`` from the summary line of ``pytest --collect-only -q``: ``"960/1091
    tests collected (131 deselected) in 14s"`` or ``"12 tests collected in 1s"``."""
    m = _COLLECTED.search(output)
    if not m:
        raise ValueError(f"pytest --collect-only printed no count:\n{output[-2000:]}")
    selected = int(m.group(1))
    return selected, int(m.group(2) or selected)


def collect_counts() -> tuple[int, int]:
    """``(fast, total)``: the tests `make test-fast` runs (marker expression :data:`FAST`) and every
    test `make test` runs, from one ``pytest --collect-only`` of tests/ (nothing runs)."""
    cmd = [sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider"]
    proc = subprocess.run([*cmd, "-m", FAST], cwd=ROOT, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise RuntimeError(
            f"pytest --collect-only failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
        )
    return parse_collected(proc.stdout)


def tests_block(fast: int, total: int) -> str:
    """docs/testing.md's generated block from the two counts."""
    text = (
        f"`make test` runs **{total:,}** tests; `make test-fast` runs the **{fast:,}** of them "
        f'that are marked neither `slow`, `integration` nor `long` (`-m "{FAST}"`; '
        f"{total - fast:,} left out)."
    )
    return "\n".join([TESTS_BEGIN, text, TESTS_END])


# ------------------------------------------------------------------ pages
def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--skip-tests",
        action="store_true",
        help="leave docs/testing.md's test counts as they are (no pytest collection)",
    )
    blocks = {CLI_PAGE: cli_block()}
    if not ap.parse_args(argv).skip_tests:
        blocks[TESTING_PAGE] = tests_block(*collect_counts())
    write_blocks({page: [block] for page, block in blocks.items()})
    print(f"{', '.join(blocks)}: generated blocks updated")


if __name__ == "__main__":
    main()
