"""Size of the reporting code: lines, the largest files and the longest functions (prints JSON).

    python -m benchmarks.code_size [--root .] [--top 10]

Reporting code = the files whose job is report sections, findings, tables, figures, templates,
README and docs generation (:data:`REPORTING`, globs relative to the repository root); every
other ``.py`` file under ``src/`` and ``pipelines/`` is counted as the rest. Lines are physical
lines (``wc -l``). Also lists, over every ``.py`` file, the functions longer than
``--max-function-lines`` and the files longer than ``--max-file-lines``.
"""

from __future__ import annotations

import argparse
import ast
import json
from collections.abc import Iterable
from pathlib import Path
from typing import Any

#: globs (relative to the repository root) of the reporting code
REPORTING = (
    "src/traffictwin/report/**/*",
    "src/traffictwin/paper_numbers.py",
    "src/traffictwin/**/report_section.py",
    "src/traffictwin/**/report_section/*.py",
    "src/traffictwin/**/report_*.py",
    "src/traffictwin/**/findings*.py",
    "src/traffictwin/**/templates/*",
    "src/traffictwin/**/figures.py",
    "src/traffictwin/**/*_figures.py",
    "src/traffictwin/**/*_figure.py",
    "src/traffictwin/**/charts.py",
    "src/traffictwin/mlops/retrain_summary.py",
    "pipelines/report.py",
    "pipelines/plot_data.py",
    "pipelines/readme_results.py",
    "pipelines/_run_records.py",
    "pipelines/templates/*",
    "pipelines/docs_reference.py",
)
CODE = ("src/**/*.py", "pipelines/**/*.py")


def _files(root: Path, globs: Iterable[str]) -> set[Path]:
    return {
        p
        for g in globs
        for p in root.glob(g)
        if p.is_file() and "__pycache__" not in p.parts and p.suffix != ".pyc"
    }


def _lines(path: Path) -> int:
    return len(path.read_bytes().splitlines())


def long_functions(path: Path, limit: int) -> list[tuple[str, int]]:
    """``(name, lines)`` of the functions and methods in ``path`` longer than ``limit`` lines."""
    tree = ast.parse(path.read_text(), filename=str(path))
    return [
        (n.name, n.end_lineno - n.lineno + 1)
        for n in ast.walk(tree)
        if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef)
        and n.end_lineno - n.lineno + 1 > limit
    ]


def measure(root: Path, top: int = 10, max_file: int = 600, max_function: int = 80) -> dict:
    """Reporting and other lines under ``root``, the ``top`` largest reporting files, the files
    over ``max_file`` lines and the functions over ``max_function`` lines (``.py`` only)."""
    reporting = _files(root, REPORTING)
    code = _files(root, CODE) | reporting
    size = {p: _lines(p) for p in code}
    rel = {p: p.relative_to(root).as_posix() for p in code}
    rep = sorted(reporting, key=lambda p: (-size[p], rel[p]))
    out: dict[str, Any] = {
        "reporting_lines": sum(size[p] for p in reporting),
        "reporting_files": len(reporting),
        "other_lines": sum(size[p] for p in code - reporting),
        "largest_reporting_files": {rel[p]: size[p] for p in rep[:top]},
        "files_over_limit": {
            rel[p]: size[p] for p in sorted(code, key=rel.get) if size[p] > max_file
        },
        "functions_over_limit": {
            f"{rel[p]}::{name}": n
            for p in sorted(code, key=rel.get)
            if p.suffix == ".py"
            for name, n in long_functions(p, max_function)
        },
    }
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--root", default=str(Path(__file__).resolve().parents[1]))
    ap.add_argument("--top", type=int, default=10)
    ap.add_argument("--max-file-lines", type=int, default=600)
    ap.add_argument("--max-function-lines", type=int, default=80)
    a = ap.parse_args(argv)
    res = measure(Path(a.root), a.top, a.max_file_lines, a.max_function_lines)
    print(json.dumps(res, indent=2))
    return res


if __name__ == "__main__":
    main()
