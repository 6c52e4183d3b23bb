"""README.md and docs/ show the committed results and the two setup commands, and work when
followed literally: their ```` ```bash ci ```` blocks run as written on the ci profile."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from pipelines import readme_results as R
from pipelines._run_records import sessions

ROOT = Path(__file__).resolve().parents[1]
#: the pages whose command blocks the documentation test follows, in the order it runs them
DOC_PAGES = ("README.md", *sorted(f"docs/{p.name}" for p in (ROOT / "docs").glob("*.md")))


def committed_records() -> list[dict]:
    """The committed run records (reports/timings/*.json at HEAD; the workspace's outside git)."""
    from conftest import committed

    names = subprocess.run(
        ["git", "ls-tree", "--name-only", "HEAD", "reports/timings/"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=False,
    ).stdout.split()
    if not names:  # outside a git checkout: the workspace's
        names = [f"reports/timings/{p.name}" for p in (ROOT / "reports" / "timings").glob("*.json")]
    return [json.loads(committed(n)) for n in sorted(names) if n.endswith(".json")]


def _generated() -> list[tuple[str, str]]:
    """``(page, block)`` of every generated block, from the committed sources."""
    from conftest import committed

    blocks = R.page_blocks(committed, committed_records())
    return [(page, block) for page, items in blocks.items() for block in items]


def _block_name(block: str) -> str:
    return block.split(":begin", 1)[0].removeprefix("<!-- ")


@pytest.mark.parametrize(
    "page,block", [pytest.param(p, b, id=f"{p}:{_block_name(b)}") for p, b in _generated()]
)
def test_generated_blocks_match_the_committed_sources(page: str, block: str) -> None:
    """Each generated block of README.md and docs/ is the one `make readme` writes from the
    *committed* reports, run records and params.yaml (read from git: a run in this checkout, e.g.
    the Quick start's, rewrites the workspace's reports/), so pages and results cannot drift apart."""
    text = (ROOT / page).read_text(encoding="utf-8")
    begin = block.splitlines()[0]
    assert begin in text, f"{page}: no generated block {begin!r}"
    assert block in text, (
        f"{page}: the block {begin!r} is stale: run `make readme` after `make run` / `make bench` "
        "and commit the page with the reports"
    )


def test_every_page_block_is_generated_somewhere() -> None:
    """Every begin marker in README.md and docs/ belongs to a block a generator writes."""
    from pipelines.docs_reference import CLI_BEGIN, TESTS_BEGIN

    known = {b.splitlines()[0] for _, b in _generated()} | {CLI_BEGIN, TESTS_BEGIN}
    for page in DOC_PAGES:
        for marker in re.findall(r"^<!-- [a-z-]+:begin .*?-->$", (ROOT / page).read_text(), re.M):
            assert marker in known, f"{page}: {marker} is written by no generator"


def test_timings_block_adds_up_the_run_records() -> None:
    def rec(stage: str, s: float, start: str, end: str) -> dict:
        m = {"cpu": "X", "cpu_count": 2, "load_start": [0.5, 0.4, 0.3], "load_end": [1, 1, 1]}
        return {"stage": stage, "seconds": s, "started": start, "finished": end, "machine": m}

    records = [
        rec("generate_fusion", 60.0, "2026-01-01T10:00:00Z", "2026-01-01T10:01:00Z"),
        rec("train_fusion", 240.0, "2026-01-01T10:01:05Z", "2026-01-01T10:05:05Z"),
        rec("prealign@A", 6.0, "2026-01-01T10:05:10Z", "2026-01-01T10:05:16Z"),
    ]
    block = R.timings_block(records)
    lines = block.splitlines()
    assert lines[0] == R.T_BEGIN and lines[-1] == R.T_END
    assert "| **5.3 min** |" in lines[3] and "X, 2 cores" in lines[3] and "0.5–0.5" in lines[3]
    assert "re-run" not in lines[3]
    assert lines[4] == "| — the stages' own time (sum of the run records, 3 stages) | 5.1 min |"
    assert (
        "| — fusion data: `generate_fusion`, `prealign@*`, `prealign_mixed`, `register@*` | 1.1 min |"
        in lines
    )
    assert any(
        ln.startswith("| — fusion and registration training") and ln.endswith("| 4.0 min |")
        for ln in lines
    )
    # the README's short table: the same first two rows, the longest stages, the budget
    short = R.run_time_block(records).splitlines()
    assert short[0] == R.TS_BEGIN and short[-1] == R.TS_END and short[3:5] == lines[3:5]
    assert short[5] == (
        "| — the 3 longest stages: `train_fusion` 4.0, `generate_fusion` 1.0, `prealign@A` 0.1 "
        "min | 5.1 min |"
    )
    assert short[6] == (
        "| the budget of `make run` on a 2-core machine | 25 min (the run above: within it) |"
    )
    slow = [rec("train_fusion", 1800.0, "2026-01-01T10:00:00Z", "2026-01-01T10:30:00Z")]
    assert "(the run above: 5.0 min over it)" in R.run_time_block(slow)
    # a stage re-run on its own an hour later: its time counts, the pause before it does not
    later = rec("report", 30.0, "2026-01-01T11:00:00Z", "2026-01-01T11:00:30Z")
    row = R.timings_block([*records, later]).splitlines()[3]
    assert "| **5.8 min** |" in row
    assert "without the pauses around `report`, run on its own at another time" in row
    assert [len(s) for s in sessions([*records, later])] == [3, 1]
    # a quick stage run an hour before the rest (dvc skipped it this time): named, not the rest
    early = rec("environment", 0.1, "2026-01-01T08:00:00Z", "2026-01-01T08:00:00Z")
    row = R.timings_block([early, *records]).splitlines()[3]
    assert "around `environment`, run on its own" in row and "generate_fusion" not in row


def test_every_timed_stage_is_in_one_timing_group() -> None:
    """The results page's per-part timing rows cover every stage that writes a run record (the
    committed ``reports/timings/<stage>.json``), each in exactly one part, so the parts add up
    to the stages' own time."""
    groups = [set(stages.split()) for _, stages in R._tpl("timing_groups")]
    names = [{s.split("@")[0] for s in g} for g in groups]
    records = (json.loads(p.read_text()) for p in (ROOT / "reports" / "timings").glob("*.json"))
    stages = {str(r["stage"]).split("@")[0] for r in records if "seconds" in r}
    for stage in sorted(stages):
        owners = [i for i, g in enumerate(names) if stage in g]
        assert len(owners) == 1, f"stage {stage}: in timing groups {owners}, expected exactly one"


def test_headline_block_is_the_reports_first_table() -> None:
    """The README's headline block: the first table of results_table.md with its title and note,
    none of the tables after it, no generated-file comment or link line."""
    results = "\n".join(
        [
            "<!-- generated by the DVC stage `report`; do not edit -->",
            "",
            "**Headline results**",
            "",
            "| problem | value |",
            "| --- | --- |",
            "| risk | 0.940 |",
            "",
            "<sub>Intervals: ...; see [fusion](pages/fusion.md).</sub>",
            "",
            "**Fusion: KLD**",
            "",
            "| config | KLD |",
            "| --- | --- |",
            "| A | 0.2 |",
            "",
            "Full report: [README.md](README.md).",
        ]
    )
    block = R.headline_block(results).splitlines()
    assert block[0] == R.H_BEGIN and block[-1] == R.H_END
    assert block[1:-1] == [
        "**Headline results**",
        "",
        "| problem | value |",
        "| --- | --- |",
        "| risk | 0.940 |",
        "",
        "<sub>Intervals: ...; see [fusion](../reports/pages/fusion.md).</sub>",
    ]
    assert "No results yet" in R.headline_block("<!-- generated -->\n\nFull report: x.")


def test_benchmarks_block_skips_what_did_not_run() -> None:
    results = {
        "environment": {"cpu": "X", "cpu_count": 2, "memory_gb": 8, "python": "3.11"},
        "benchmarks": {
            "fusion_data": {
                "generation_pairs_per_s_1core": 33.51,
                "machine": {"cpu": "X", "cores": 2},
            },
            "twin": {"broken": True},
        },
    }
    block = R.benchmarks_block(results)
    lines = block.splitlines()
    assert lines[0] == R.B_BEGIN and lines[-1] == R.B_END
    assert "Last `make bench`: X, 2 cores, 8 GB, no GPU; Python 3.11." in block
    rows = [ln for ln in lines if ln.startswith("| ") and "---" not in ln][1:]
    assert len(rows) == 1 and "| 33.5 pairs/s | X, 2 cores |" in rows[0]


def test_readme_names_the_two_commands() -> None:
    readme = (ROOT / "README.md").read_text()
    assert "make run" in readme and "make test" in readme


def test_readme_stays_a_few_screens_long() -> None:
    """The README is the front page (what, quick start, headline results, where next); the rest
    lives in docs/."""
    n = len((ROOT / "README.md").read_text().splitlines())
    assert n <= 300, f"README.md has {n} lines: move reference material to docs/"


def test_every_docs_page_is_linked_from_the_readme() -> None:
    readme = (ROOT / "README.md").read_text()
    for page in DOC_PAGES[1:]:
        assert f"]({page})" in readme or f"]({page}#" in readme, f"README.md does not link {page}"


def test_render_replaces_only_the_block() -> None:
    text = f"intro\n{R.BEGIN}\nold\n{R.END}\noutro\n"
    table = "<!-- generated -->\n| a |\n| --- |\n| 1 |\nFull report: [README.md](README.md).\n"
    block = R.results_block(table)
    assert R.render("docs/results.md", text, [block]) == f"intro\n{block}\noutro\n"
    assert block == f"{R.BEGIN}\n| a |\n| --- |\n| 1 |\n{R.END}"
    # a link to a page of the report points at that page from docs/
    paged = R.results_block("| [fusion](pages/fusion.md#x) |\n")
    assert paged == f"{R.BEGIN}\n| [fusion](../reports/pages/fusion.md#x) |\n{R.END}"
    with pytest.raises(ValueError, match="docs/results.md: markers missing"):
        R.render("docs/results.md", "no markers", [block])


# ------------------------------------------------------------------ the README, followed literally
#: the info string of a fenced shell block that is safe and fast on the ci profile
CI_TAG = "bash ci"
_FENCE = re.compile(r"^```([^\n`]*)\n(.*?)^```[ \t]*$", re.M | re.S)


def fenced_blocks(text: str) -> list[tuple[str, str]]:
    """``(info string, body)`` of every fenced code block of a Markdown ``text``, in order."""
    return [(m.group(1).strip(), m.group(2)) for m in _FENCE.finditer(text)]


def ci_blocks(text: str) -> list[str]:
    """The bodies of the blocks tagged ```` ```bash ci ````, in order."""
    return [body for info, body in fenced_blocks(text) if info == CI_TAG]


def test_fenced_blocks_parses_info_strings_and_bodies() -> None:
    md = "a\n```bash ci\necho 1\n```\ntext\n```\nplain\n```\n```bash\nmake run\n```\n"
    assert fenced_blocks(md) == [("bash ci", "echo 1\n"), ("", "plain\n"), ("bash", "make run\n")]
    assert ci_blocks(md) == ["echo 1\n"]


def _commands(block: str) -> list[str]:
    """The shell commands of a block: comment and continuation lines joined, comments dropped."""
    joined = re.sub(r"\\\n\s*", " ", block)
    lines = (ln.split("  #")[0].strip() for ln in joined.splitlines())
    return [ln for ln in lines if ln and not ln.startswith("#")]


def documented_ci_blocks(root: Path = ROOT) -> list[tuple[str, str]]:
    """``(page, body)`` of every ```` ```bash ci ```` block of README.md and of every page in
    docs/ under ``root``: the README first (its Quick start builds what the others use), then the
    pages in name order, each page's blocks in their order."""
    pages = ["README.md", *sorted(f"docs/{p.name}" for p in (root / "docs").glob("*.md"))]
    return [(page, body) for page in pages for body in ci_blocks((root / page).read_text())]


def test_documented_ci_blocks_come_from_the_readme_then_the_docs_pages(tmp_path: Path) -> None:
    (tmp_path / "docs").mkdir()
    (tmp_path / "README.md").write_text("```bash ci\nreadme 1\n```\n```bash\nmake run\n```\n")
    (tmp_path / "docs" / "b.md").write_text("```bash ci\nb 1\n```\ntext\n```bash ci\nb 2\n```\n")
    (tmp_path / "docs" / "a.md").write_text("```bash\nnot ci\n```\n```bash ci\na 1\n```\n")
    (tmp_path / "docs" / "notes.txt").write_text("```bash ci\nnot a page\n```\n")
    assert documented_ci_blocks(tmp_path) == [
        ("README.md", "readme 1\n"),
        ("docs/a.md", "a 1\n"),
        ("docs/b.md", "b 1\n"),
        ("docs/b.md", "b 2\n"),
    ]


def test_the_docs_pages_ci_blocks_are_collected() -> None:
    """The real pages: the README's Quick start first, and the quick experiments of
    docs/experiments.md (moved there from the README) among the blocks the slow test runs."""
    blocks = documented_ci_blocks()
    pages = [page for page, _ in blocks]
    assert pages[0] == "README.md" and pages == sorted(pages, key=DOC_PAGES.index)
    assert "docs/experiments.md" in pages
    cmds = [c for _, b in blocks for c in _commands(b)]
    assert cmds[0] == "source .venv/bin/activate" and cmds[1].startswith(
        "dvc exp run -S profile=ci"
    )
    assert any(c.startswith("dvc exp run -n lr-high") for c in cmds)


@pytest.mark.parametrize("page", DOC_PAGES)
def test_commands_are_make_targets_or_run_in_the_activated_venv(page: str) -> None:
    """Every shell command is a `make` target or comes after the README's one
    `source .venv/bin/activate` (then `dvc`, `python`, `traffictwin`, `mlflow` are .venv's, with
    no `.venv/bin/` prefix mixed in, in the README or any docs page); quick (ci-tagged) experiments
    say `-S profile=ci`, and no ci-tagged block resets or rebuilds the workspace."""
    text = (ROOT / page).read_text()
    assert ".venv/bin/" not in text.replace("source .venv/bin/activate", ""), (
        f"{page} mixes .venv/bin/ prefixes with the activated environment"
    )
    if page == "README.md":
        first = text.index("## Quick start")
        assert first < text.index("## Two commands"), "Quick start must come first"
        activate = text.index("source .venv/bin/activate")
        for m in _FENCE.finditer(text):
            if m.group(1).strip().startswith("bash") and m.end() < activate:
                for cmd in _commands(m.group(2)):
                    assert cmd.split()[0] == "make", f"before `source .venv/bin/activate`: {cmd}"
    quick = [c for info, b in fenced_blocks(text) if info == CI_TAG for c in _commands(b)]
    for cmd in quick:
        if cmd.startswith("dvc exp run"):
            assert "-S profile=ci" in cmd, (
                f"{page}: a quick experiment without -S profile=ci: {cmd}"
            )
        assert not re.match(r"make (reset|run|install|retrain|test)\b", cmd), (
            f"{page}: `{cmd}` is no quick ci step: tag its block plain `bash`"
        )


def test_readme_cli_examples_use_the_committed_sample_poses() -> None:
    """The Quick start's `traffictwin fuse` passes exactly examples/fuse/ci/poses.json's poses."""
    meta = json.loads((ROOT / "examples/fuse/ci/poses.json").read_text())
    risk = json.loads((ROOT / "examples/risk/000.json").read_text())
    cmds = [c for b in ci_blocks((ROOT / "README.md").read_text()) for c in _commands(b)]
    fuse = [c for c in cmds if c.startswith("traffictwin fuse")]
    assert fuse and all(
        f"--pose1={meta['pose1']}" in c and f"--pose2={meta['pose2']}" in c for c in fuse
    )
    assert any(
        c.startswith("traffictwin risk") and f"--speed {risk['speed_m_s']}" in c for c in cmds
    )


@pytest.mark.slow
def test_readme_ci_blocks_run_as_written(ci_dag: Path, tmp_path: Path) -> None:
    """Follow the ```` ```bash ci ```` blocks of the README and of every docs page
    (:func:`documented_ci_blocks`), in order, in one shell, in a clone of the finished ci DAG (so
    its `dvc exp run -S profile=ci` finds every stage up to date instead of running the DAG a
    second time), with the MLflow runs the Quick start's DAG logged (`runs compare` reads them);
    then checks what the docs' experiments show (test_experiments.check_documented_experiments).
    `make install` is not run: the tests' own venv stands in for `.venv`, which must not be
    reinstalled from a temp copy."""
    from conftest import run
    from test_experiments import check_documented_experiments, clone_dag, user_env

    repo = clone_dag(ci_dag, tmp_path / "readme_repo", mlflow=True)
    (repo / ".venv").symlink_to(Path(sys.prefix), target_is_directory=True)
    blocks = [body for _, body in documented_ci_blocks(repo)]
    assert len(blocks) >= 3, "the Quick start and a quick experiment should be tagged ci"
    script = "set -euo pipefail\n" + "\n".join(blocks)
    proc = run(["bash", "-c", script], repo, env=user_env(repo), timeout=1500)
    assert (repo / "outputs/fused.npz").is_file() and (repo / "outputs/fused.png").is_file()
    assert '"verdict"' in proc.stdout  # traffictwin risk printed its JSON
    assert "lr-high" in proc.stdout and (repo / "plots_cmp").is_dir()
    # runs compare: the fusion runs named by the experiments, and the risk runs
    assert "fusion-network [lr-high: fusion_model.optim.lr=0.02]" in proc.stdout
    assert "risk-headline" in proc.stdout
    # the docs' two learning-rate experiments, as DVC and MLflow show them
    check_documented_experiments(repo, user_env(repo))
