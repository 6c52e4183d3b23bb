"""The DVC remote story: the repository's default remote is a folder beside the clone, `make push`
fills it, and a second clone on the same machine gets data and models back with `make pull`
(`dvc status` clean: no stage needs to run again)."""

from __future__ import annotations

import configparser
import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import run
from test_experiments import clone_dag, user_env

ROOT = Path(__file__).resolve().parents[1]


def default_remote(config: Path) -> tuple[str, Path]:
    """Name and resolved URL of the default remote in a DVC ``config`` (relative to ``.dvc/``)."""
    cp = configparser.ConfigParser()
    cp.read_string(config.read_text())
    name = cp["core"]["remote"]
    # DVC writes the section as ['remote "name"'] (quotes included in configparser's name)
    url = next(cp[sec]["url"] for sec in cp.sections() if sec.strip("'") == f'remote "{name}"')
    return name, (config.parent / url).resolve()


def test_default_remote_is_a_local_folder_outside_the_repository() -> None:
    name, url = default_remote(ROOT / ".dvc" / "config")
    assert name and "://" not in str(url)
    assert url.parent == ROOT.resolve().parent, f"{url} is not beside the clone"
    assert not url.is_relative_to(ROOT.resolve())


def make(repo: Path, target: str, env: dict[str, str]) -> subprocess.CompletedProcess:
    """``make TARGET`` as the README says, except that the venv counts as installed (``-o``: the
    test's interpreter stands in for .venv, which must not be reinstalled from a temp copy)."""
    return run(["make", "-o", ".venv/.install-stamp", target], repo, env=env, timeout=600)


def link_venv(repo: Path) -> None:
    """``repo/.venv`` -> the venv running the tests (what `make install` would have made)."""
    (repo / ".venv").symlink_to(Path(sys.prefix), target_is_directory=True)


@pytest.mark.slow
def test_push_then_pull_in_a_second_clone(ci_dag: Path, tmp_path: Path) -> None:
    first = clone_dag(ci_dag, tmp_path / "first")
    link_venv(first)
    env = user_env(first)
    store = tmp_path / "traffictwin-dvc-store"
    assert default_remote(first / ".dvc" / "config")[1] == store
    make(first, "push", env)
    assert any(p.is_file() for p in store.rglob("*")), "make push sent nothing to the remote"

    second = tmp_path / "second"  # beside the first: the same relative remote
    subprocess.run(["git", "clone", "-q", str(first), str(second)], check=True)
    link_venv(second)
    env2 = user_env(second)
    assert not (second / "models").exists() and not (second / "data").exists()
    make(second, "pull", env2)
    for rel in (
        "models/fusion/network/model.ckpt",
        "models/risk/headline",
        "data/fusion/manifest.json",
    ):
        assert (second / rel).exists(), f"{rel} not pulled"
    assert (second / "models/fusion/network/model.ckpt").read_bytes() == (
        first / "models/fusion/network/model.ckpt"
    ).read_bytes()
    status = run(["dvc", "status", "--json"], second, env=env2).stdout.strip()
    assert status in ("{}", ""), f"dvc status after pull is not clean: {status[:2000]}"
    assert os.listdir(store)  # the store is outside both clones
