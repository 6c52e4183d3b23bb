"""benchmarks/code_size.py: which files count as reporting code, their lines, and the files and
functions over the limits, on a hand-made tree."""

from __future__ import annotations

from pathlib import Path

from benchmarks import code_size as C


def _write(root: Path, rel: str, lines: int, body: str | None = None) -> None:
    p = root / rel
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(body if body is not None else "x = 1\n" * lines)


def test_reporting_and_other_lines_on_a_small_tree(tmp_path: Path) -> None:
    _write(tmp_path, "src/traffictwin/report/render.py", 5)
    _write(tmp_path, "src/traffictwin/report/templates/page.md.j2", 3)
    _write(tmp_path, "src/traffictwin/risk/report_section.py", 4)
    _write(tmp_path, "src/traffictwin/fusion/report_section/tables.py", 2)
    _write(tmp_path, "src/traffictwin/risk/findings_data.py", 6)
    _write(tmp_path, "src/traffictwin/twin/figures.py", 7)
    _write(tmp_path, "pipelines/report.py", 1)
    _write(tmp_path, "src/traffictwin/risk/metric.py", 10)  # not reporting
    _write(tmp_path, "pipelines/train_risk.py", 20)  # not reporting
    long = "def f():\n" + "    x = 1\n" * 90 + "\n\ndef g():\n    return 1\n"
    _write(tmp_path, "src/traffictwin/fusion/methods.py", 0, long)
    res = C.measure(tmp_path, top=2, max_file=15, max_function=80)
    assert res["reporting_files"] == 7
    assert res["reporting_lines"] == 5 + 3 + 4 + 2 + 6 + 7 + 1
    assert res["other_lines"] == 10 + 20 + long.count("\n")
    assert res["largest_reporting_files"] == {
        "src/traffictwin/twin/figures.py": 7,
        "src/traffictwin/risk/findings_data.py": 6,
    }
    assert set(res["files_over_limit"]) == {
        "pipelines/train_risk.py",
        "src/traffictwin/fusion/methods.py",
    }
    assert res["functions_over_limit"] == {"src/traffictwin/fusion/methods.py::f": 91}


def test_the_repository_counts_its_report_renderer_and_not_its_training() -> None:
    root = Path(__file__).resolve().parents[1]
    reporting = {p.relative_to(root).as_posix() for p in C._files(root, C.REPORTING)}
    assert "src/traffictwin/report/render.py" in reporting
    assert "pipelines/report.py" in reporting
    assert "pipelines/train_risk.py" not in reporting
    assert "src/traffictwin/risk/metric.py" not in reporting
