"""README.md shows the committed report's numbers and the two setup commands, and works when
followed literally: its ```` ```bash ci ```` blocks run as written on the ci profile."""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import pytest

from pipelines.readme_results import BEGIN, END, render, results_block

ROOT = Path(__file__).resolve().parents[1]


def test_readme_results_match_the_committed_report() -> None:
    """The committed README shows the committed report's numbers (read from git: a run in this
    checkout, e.g. the Quick start's, rewrites the workspace's reports/)."""
    from conftest import committed

    readme = committed("README.md")
    table = committed("reports/results_table.md")
    assert results_block(table) in readme, (
        "README.md results are stale: run `make readme` after `make run`"
    )


def test_readme_timings_match_the_committed_run_records() -> None:
    """The committed README's timing table is the one `make readme` writes from the committed run
    records (reports/timings/*.json), so the two cannot drift apart."""
    import subprocess

    from conftest import committed

    from pipelines.readme_results import timings_block

    names = subprocess.run(
        ["git", "ls-tree", "--name-only", "HEAD", "reports/timings/"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=False,
    ).stdout.split()
    if not names:  # outside a git checkout: the workspace's
        names = [f"reports/timings/{p.name}" for p in (ROOT / "reports" / "timings").glob("*.json")]
    records = [json.loads(committed(n)) for n in sorted(names) if n.endswith(".json")]
    assert timings_block(records) in committed("README.md"), (
        "README.md timings are stale: run `make readme` after `make run`"
    )


def test_timings_block_adds_up_the_run_records() -> None:
    from pipelines.readme_results import T_BEGIN, T_END, timings_block

    def rec(stage: str, s: float, start: str, end: str) -> dict:
        m = {"cpu": "X", "cpu_count": 2, "load_start": [0.5, 0.4, 0.3], "load_end": [1, 1, 1]}
        return {"stage": stage, "seconds": s, "started": start, "finished": end, "machine": m}

    block = timings_block(
        [
            rec("generate_fusion", 60.0, "2026-01-01T10:00:00Z", "2026-01-01T10:01:00Z"),
            rec("train_fusion", 240.0, "2026-01-01T10:01:05Z", "2026-01-01T10:05:05Z"),
            rec("prealign@A", 6.0, "2026-01-01T10:05:10Z", "2026-01-01T10:05:16Z"),
        ]
    )
    lines = block.splitlines()
    assert lines[0] == T_BEGIN and lines[-1] == T_END
    assert "| **5.3 min** |" in lines[3] and "X, 2 cores" in lines[3] and "0.5–0.5" in lines[3]
    assert lines[4] == "| — the stages' own time (sum of the run records, 3 stages) | 5.1 min |"
    assert (
        "| — fusion data: `generate_fusion`, `prealign@*`, `prealign_mixed`, `register@*` | 1.1 min |"
        in lines
    )
    assert any(
        ln.startswith("| — fusion and registration training") and ln.endswith("| 4.0 min |")
        for ln in lines
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


def test_readme_commands_are_make_targets_or_run_in_the_activated_venv() -> None:
    """Every shell command is a `make` target or comes after the one `source .venv/bin/activate`
    (then `dvc`, `python`, `traffictwin`, `mlflow` are .venv's, with no `.venv/bin/` prefix mixed
    in); quick (ci-tagged) experiments say `-S profile=ci`."""
    readme = (ROOT / "README.md").read_text()
    assert ".venv/bin/" not in readme.replace("source .venv/bin/activate", ""), (
        "mixes .venv/bin/ prefixes with the activated environment"
    )
    first = readme.index("## Quick start")
    assert first < readme.index("## Two commands"), "Quick start must come first"
    activate = readme.index("source .venv/bin/activate")
    for m in _FENCE.finditer(readme):
        if not m.group(1).strip().startswith("bash"):
            continue
        if m.end() < activate:
            for cmd in _commands(m.group(2)):
                assert cmd.split()[0] == "make", f"before `source .venv/bin/activate`: {cmd}"
    quick = [c for info, b in fenced_blocks(readme) if info == CI_TAG for c in _commands(b)]
    for cmd in quick:
        if cmd.startswith("dvc exp run"):
            assert "-S profile=ci" in cmd, f"a quick experiment without -S profile=ci: {cmd}"


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
    """Follow the README's ```` ```bash ci ```` blocks, in order, in one shell, in a clone of the
    finished ci DAG (so its `dvc exp run -S profile=ci` finds every stage up to date instead of
    running the DAG a second time). `make install` is not run: the tests' own venv stands in for
    `.venv`, which must not be reinstalled from a temp copy."""
    from conftest import run
    from test_experiments import clone_dag, user_env

    repo = clone_dag(ci_dag, tmp_path / "readme_repo")
    (repo / ".venv").symlink_to(Path(sys.prefix), target_is_directory=True)
    blocks = ci_blocks((repo / "README.md").read_text())
    assert len(blocks) >= 3, "the Quick start and a quick experiment should be tagged ci"
    script = "set -euo pipefail\n" + "\n".join(blocks)
    proc = run(["bash", "-c", script], repo, env=user_env(repo), timeout=1500)
    assert (repo / "outputs/fused.npz").is_file() and (repo / "outputs/fused.png").is_file()
    assert '"verdict"' in proc.stdout  # traffictwin risk printed its JSON
    assert "ow3" in proc.stdout and (repo / "plots_cmp").is_dir()
