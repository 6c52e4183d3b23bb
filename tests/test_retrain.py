"""Scheduled retraining: lock, seed bump as a Hydra override, restore on failure, end to end on the ci profile."""

from __future__ import annotations

import fcntl
import json
import sys
from pathlib import Path

import pytest
import yaml
from conftest import run, stage_env

from pipelines import _checkout as ck
from pipelines import retrain as rt
from traffictwin.config import ConfigError, compose_config, load_params
from traffictwin.mlops import registry as reg
from traffictwin.mlops.config import compose_with_seeds, seed_overrides
from traffictwin.mlops.journal import LockBusy, Snapshot, exclusive_lock

# the e2e test retrains and gates the risk net only: the gate is one code path for every registered
# model (tests/test_promote.py gates the fusion network and the others), and the risk chain is the
# shortest one a new seed re-runs (4 stages; the fusion network's is 9)
MODELS = ["traffictwin-risk"]


# ------------------------------------------------------------------ fast unit tests


def test_lock_is_exclusive(tmp_path):
    lock = tmp_path / ".retrain.lock"
    with exclusive_lock(lock, "retraining run"):
        with pytest.raises(
            LockBusy, match=r"another retraining run holds the lock .*\.retrain\.lock \(pid \d+"
        ):
            with exclusive_lock(lock, "retraining run"):
                pass
    with exclusive_lock(lock, "retraining run"):  # released after the block
        pass


def test_seed_overrides_compose_without_editing_conf(tmp_path):
    conf = tmp_path / "conf"
    (conf / "risk_data").mkdir(parents=True)
    (conf / "profile").mkdir()
    (conf / "config.yaml").write_text(
        "defaults:\n  - _self_\n  - risk_data: base\n  - profile: ci\n\nseed: 41   # global\ngrid:\n  seed: 3\n"
    )
    (conf / "risk_data" / "base.yaml").write_text("seed: 0   # offset\nother: 1\n")
    (conf / "profile" / "ci.yaml").write_text("name: ci\n")
    before = {p: p.read_text() for p in conf.rglob("*.yaml")}
    cfg = compose_config(conf, ["profile=ci"])
    seeds = seed_overrides(cfg, ["seed", "risk_data.seed"], 1, None)
    assert seeds == {"seed": (41, 42), "risk_data.seed": (0, 1)}
    assert seed_overrides(cfg, ["seed"], 1, 7) == {"seed": (41, 7)}
    composed, overrides = compose_with_seeds(conf, "ci", seeds)
    assert overrides == ["profile=ci", "seed=42", "risk_data.seed=1"]
    assert composed["seed"] == 42 and composed["grid"]["seed"] == 3  # nested key untouched
    assert composed["risk_data"] == {"seed": 1, "other": 1}
    assert composed == compose_config(conf, overrides)
    assert {p: p.read_text() for p in conf.rglob("*.yaml")} == before  # conf/ never edited
    with pytest.raises(ConfigError, match="key 'nope' is missing"):
        seed_overrides(cfg, ["nope"], 1, None)


def test_data_versions_reads_dvc_lock(tmp_path):
    (tmp_path / "dvc.lock").write_text(
        yaml.safe_dump(
            {
                "schema": "2.0",
                "stages": {
                    "gen": {
                        "cmd": "x",
                        "outs": [
                            {"path": "data/fusion", "md5": "abc.dir"},
                            {"path": "reports/m.json", "md5": "1"},
                        ],
                    },
                    "train": {"cmd": "y", "outs": [{"path": "models/fusion/network", "md5": "m"}]},
                },
            }
        )
    )
    assert ck.data_versions(tmp_path) == {"data/fusion": "abc.dir"}
    assert ck.data_versions(tmp_path / "nowhere") == {}


def test_snapshot_restores_conf_params_reports(tmp_path):
    root = tmp_path / "r"
    (root / "conf").mkdir(parents=True)
    (root / "reports").mkdir()
    (root / "conf" / "config.yaml").write_text("seed: 1\n")
    (root / "params.yaml").write_text("seed: 1\n")
    (root / "reports" / "a.json").write_text("{}")
    snap_dir = tmp_path / "snap"
    snap_dir.mkdir()
    snap = Snapshot(root, snap_dir, ck.RESTORED)
    (root / "conf" / "config.yaml").write_text("seed: 2\n")
    (root / "params.yaml").write_text("seed: 2\n")
    (root / "reports" / "a.json").write_text('{"new": 1}')
    (root / "reports" / "b.json").write_text("{}")
    (root / "dvc.lock").write_text("schema: '2.0'\n")  # created by the failed run: removed again
    snap.restore_files()
    assert (root / "conf" / "config.yaml").read_text() == "seed: 1\n" and (
        root / "params.yaml"
    ).read_text() == "seed: 1\n"
    assert (
        sorted(p.name for p in (root / "reports").iterdir()) == ["a.json"]
        and (root / "reports" / "a.json").read_text() == "{}"
    )
    assert not (root / "dvc.lock").exists()


# ------------------------------------------------------------------ end to end (ci profile)


def _champions(repo: Path) -> dict[str, str | None]:
    cl = reg.client(f"sqlite:///{repo / 'mlflow.db'}")
    return {
        n: (None if (mv := reg.get_alias(cl, n, "champion")) is None else str(mv.version))
        for n in MODELS
    }


def _cheap_copy(repo: Path) -> Path:
    """Keep the e2e test cheap: start without history; gate (--only) and repro only what MODELS
    need. The copy's registry gates the headline risk network (``registry.risk.variant``) rather
    than the shipped predictor, whose choice (``select_risk``) needs every risk variant, the
    learned stereo and the hybrid trained first: the gate is the same code for either, and the
    shipped predictor's gate runs in tests/test_readme.py (docs/registry.md's promotion)."""
    for name in (
        "promotions.jsonl",
        "retrain_summary.json",
        "retrain_summary.md",
    ):  # start without history
        (repo / "reports" / name).unlink(missing_ok=True)
    registry = repo / "conf" / "registry" / "base.yaml"
    text = registry.read_text()
    assert "  variant: shipped" in text, "conf/registry/base.yaml: the risk gate's variant moved"
    registry.write_text(text.replace("  variant: shipped", "  variant: headline", 1))
    return repo


# the risk net and what a new seed re-runs under it: generate_risk, disparity, orb_filter
TARGETS = ["train_risk@headline"]


@pytest.mark.slow
def test_retrain_end_to_end_lock_and_failure_restore(repo_copy: Path):
    repo = _cheap_copy(repo_copy)
    seed0 = load_params(repo / "params.yaml")["seed"]

    # 1. a retraining on the ci profile: new seed in conf/, dvc repro, first models become champions
    conf0 = (repo / "conf" / "config.yaml").read_text()
    proc = run(
        [sys.executable, "-m", "pipelines.retrain", "--targets", *TARGETS, "--only", *MODELS],
        repo,
        timeout=1500,
    )
    summary = json.loads((repo / "reports" / "retrain_summary.json").read_text())
    assert summary["status"] == "succeeded", proc.stderr[-3000:]
    assert summary["seeds"] == {"seed": [seed0, seed0 + 1]}
    assert summary["overrides"] == ["profile=ci", f"seed={seed0 + 1}"]
    assert (repo / "conf" / "config.yaml").read_text() == conf0  # conf/ is never edited
    params = yaml.safe_load((repo / "params.yaml").read_text())
    assert params == compose_config(repo / "conf", summary["overrides"])
    assert params["seed"] == seed0 + 1
    assert summary["data_after"]["data/risk"] != summary["data_before"]["data/risk"]  # new data
    champs = _champions(repo)
    assert all(v == "1" for v in champs.values()), champs
    log = reg.read_log(repo / "reports" / "promotions.jsonl")
    assert sorted(r["name"] for r in log) == sorted(MODELS) and {r["action"] for r in log} == {
        "first"
    }
    assert all(r["challenger_value"] is not None and r["test_fingerprint"] for r in log)
    md = (repo / "reports" / "retrain_summary.md").read_text()
    assert "Retraining succeeded" in md and "traffictwin-risk" in md

    lock_before = (repo / "dvc.lock").read_text()
    params_before = (repo / "params.yaml").read_text()
    conf_before = (repo / "conf" / "config.yaml").read_text()

    # 2. a second run while one holds the lock exits 75 with the lock message and changes nothing
    with open(repo / ".retrain.lock", "a+") as fh:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        busy = run([sys.executable, "-m", "pipelines.retrain"], repo, check=False, timeout=300)
    assert busy.returncode == rt.EXIT_LOCKED
    assert "another retraining run holds the lock" in busy.stderr
    assert (repo / "params.yaml").read_text() == params_before

    # 3. a failure after new data were generated restores data, params, conf; champion unchanged
    env = stage_env(repo)
    env[rt.FAIL_ENV] = "after_repro"
    failed = run(
        [
            sys.executable,
            "-m",
            "pipelines.retrain",
            "--targets",
            "generate_risk",
        ],
        repo,
        check=False,
        timeout=900,
        env=env,
    )
    assert failed.returncode == 1 and "injected failure at 'after_repro'" in failed.stderr
    s2 = json.loads((repo / "reports" / "retrain_summary.json").read_text())
    assert s2["status"] == "failed" and s2["restored"] is True, (
        s2.get("restore_problems"),
        failed.stderr[-3000:],
    )
    assert (
        s2["data_after"]["data/risk"] != summary["data_after"]["data/risk"]
    )  # new data had been made ...
    assert (repo / "dvc.lock").read_text() == lock_before  # ... and were rolled back
    assert (repo / "params.yaml").read_text() == params_before
    assert (repo / "conf" / "config.yaml").read_text() == conf_before
    status = run(["dvc", "status", "generate_risk"], repo)
    assert "up to date" in status.stdout, status.stdout
    assert _champions(repo) == champs
    assert len(reg.read_log(repo / "reports" / "promotions.jsonl")) == len(log)
