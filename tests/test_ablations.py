"""Ablations (pipelines/ablations.py): named override lists in params.yaml, run as DVC experiments,
their evaluation blocks collected into reports/ablations/<name>.json for the report."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest
from omegaconf import OmegaConf

import pipelines.ablations as ab
from traffictwin.config import ConfigError

GIT = ["git", "-c", "user.email=t@t", "-c", "user.name=t", "-c", "commit.gpgsign=false"]


def test_ablations_are_named_override_lists() -> None:
    cfg = OmegaConf.create({"ablations": {"fusion": ["fusion_variants=ablations", "a.b=[1,2]"]}})
    assert ab.ablations(cfg) == {"fusion": ["fusion_variants=ablations", "a.b=[1,2]"]}
    with pytest.raises(ConfigError, match="'ablations.x' must be a list of Hydra overrides"):
        ab.ablations(OmegaConf.create({"ablations": {"x": "fusion_variants=ablations"}}))


def test_the_project_defines_the_fusion_and_risk_ablations() -> None:
    from traffictwin.config import compose_config

    cfg = compose_config(ab.ROOT / "conf", [])
    todo = ab.ablations(cfg)
    assert set(todo) == {
        "per_config",
        "losses",
        "registered",
        "plain_network",
        "seeds_1",
        "seeds_2",
        "fp32",
        "risk",
    }
    # each ablation's overrides compose (what `dvc exp run -S` will hand to Hydra)
    for overrides in todo.values():
        composed = compose_config(ab.ROOT / "conf", overrides)
        assert composed != cfg
    per = compose_config(ab.ROOT / "conf", todo["per_config"])
    assert set(per["fusion_variants"]) == {"A", "B", "C", "D"}  # the per-configuration networks
    assert "train" in per["fusion_data"]["prealign"]["splits"]  # ... need their train splits
    reg = compose_config(ab.ROOT / "conf", todo["registered"])
    assert reg["fusion_data"]["register"]["configurations"] == ["mixed"]
    assert compose_config(ab.ROOT / "conf", todo["fp32"])["trainer"]["precision"] == "32-true"
    # the paper's plain network against the default residual head on Dempster's combination
    assert cfg["fusion_model"]["architecture"]["residual"] == "dempster"
    plain = compose_config(ab.ROOT / "conf", todo["plain_network"])
    assert plain["fusion_model"]["architecture"]["residual"] == "none"
    # the seed replicates change the two trainings' seeds and nothing else (same data)
    for k in (1, 2):
        rep = compose_config(ab.ROOT / "conf", todo[f"seeds_{k}"])
        assert rep["fusion_model"]["train"]["seed_offset"] == k
        assert rep["registration_model"]["train"]["seed_offset"] == k
        rep["fusion_model"]["train"]["seed_offset"] = 0
        rep["registration_model"]["train"]["seed_offset"] = 0
        assert rep == cfg


def _repo(tmp_path: Path) -> Path:
    repo = tmp_path / "repo"
    (repo / "reports" / "metrics").mkdir(parents=True)
    subprocess.run([*GIT, "init", "-q"], cwd=repo, check=True)
    (repo / "reports" / "metrics" / "x.json").write_text("{}")
    subprocess.run([*GIT, "add", "-A"], cwd=repo, check=True)
    subprocess.run([*GIT, "commit", "-qm", "base"], cwd=repo, check=True)
    fusion = {
        "test": {"D": {"dnn[per-config]": {"kld_fou_mean": 0.05}}},
        "diff": {"D": {}},
        "targets": {"one_vs_per_config": {"status": "pass"}},
        "n_pairs": {"per_config": 200},  # not kept: only what the report shows
    }
    (repo / "reports" / "metrics" / "fusion.json").write_text(json.dumps(fusion))
    subprocess.run([*GIT, "add", "-A"], cwd=repo, check=True)
    subprocess.run([*GIT, "commit", "-qm", "exp"], cwd=repo, check=True)
    rev = subprocess.run(
        ["git", "rev-parse", "HEAD"], cwd=repo, capture_output=True, text=True, check=True
    ).stdout.strip()
    # where `dvc exp run -n ablation-fusion` keeps its result
    subprocess.run(
        ["git", "update-ref", "refs/exps/ab/cdef/ablation-fusion", rev], cwd=repo, check=True
    )
    subprocess.run([*GIT, "reset", "-q", "--hard", "HEAD~1"], cwd=repo, check=True)
    return repo


def test_collect_copies_the_experiments_evaluation_blocks(tmp_path, monkeypatch) -> None:
    repo = _repo(tmp_path)
    monkeypatch.setattr(ab, "ROOT", repo)
    monkeypatch.setattr(ab, "ABLATIONS", repo / "reports" / "ablations")
    res = ab.collect("fusion", ["fusion_variants=ablations"])
    saved = json.loads((repo / "reports" / "ablations" / "fusion.json").read_text())
    assert saved == res
    assert saved["experiment"] == "ablation-fusion" and saved["overrides"] == [
        "fusion_variants=ablations"
    ]
    assert set(saved["fusion"]) == {"test", "diff", "targets"} and "risk" not in saved
    assert saved["fusion"]["test"]["D"]["dnn[per-config]"]["kld_fou_mean"] == 0.05
    assert len(saved["commit"]) == 40 and saved["baseline"] != saved["commit"]
    with pytest.raises(RuntimeError, match="no DVC experiment ablation-risk"):
        ab.collect("risk", [])


def test_unknown_ablation_is_one_error_line(capsys) -> None:
    assert ab.main(["collect", "nope"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("ablations: error: unknown ablation(s) ['nope']") and err.count("\n") == 1


def test_run_hands_the_overrides_and_the_last_stage_to_dvc_exp_run(monkeypatch) -> None:
    calls: list[list[str]] = []
    monkeypatch.setattr(ab.subprocess, "run", lambda cmd, **kw: calls.append(cmd))
    ab.run("seeds_1", ["fusion_model.train.seed_offset=1", "a.b=2"], until="evaluate_fusion")
    ab.run("fp32", ["trainer.precision=32-true"])
    assert calls == [
        [
            "dvc",
            "exp",
            "run",
            "--temp",
            "-n",
            "ablation-seeds_1",
            "-S",
            "fusion_model.train.seed_offset=1",
            "-S",
            "a.b=2",
            "evaluate_fusion",
        ],
        ["dvc", "exp", "run", "--temp", "-n", "ablation-fp32", "-S", "trainer.precision=32-true"],
    ]


def test_seed_replicates_are_collected_against_their_baseline_run(tmp_path, monkeypatch) -> None:
    from tests.test_fusion_seeds import _samples

    repo = tmp_path / "repo"
    (repo / "reports").mkdir(parents=True)
    subprocess.run([*GIT, "init", "-q"], cwd=repo, check=True)
    csv = repo / ab.FUSION_SAMPLES

    def commit(frame, msg: str) -> str:
        frame.to_csv(csv, index=False)
        subprocess.run([*GIT, "add", "-A"], cwd=repo, check=True)
        subprocess.run([*GIT, "commit", "-qm", msg], cwd=repo, check=True)
        return subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=repo, capture_output=True, text=True, check=True
        ).stdout.strip()

    base = commit(_samples(), "default run")
    for k in (1, 2):  # each experiment: a child commit of the baseline with its own samples
        rev = commit(_samples(shift=-0.01 * k), f"seed {k}")
        subprocess.run(
            ["git", "update-ref", f"refs/exps/ab/cd/ablation-seeds_{k}", rev], cwd=repo, check=True
        )
        subprocess.run([*GIT, "reset", "-q", "--hard", base], cwd=repo, check=True)
    monkeypatch.setattr(ab, "ROOT", repo)
    monkeypatch.setattr(ab, "ABLATIONS", repo / "reports" / "ablations")
    monkeypatch.setattr(ab, "FUSION_SEEDS", repo / "reports" / "ablations" / "fusion_seeds.json")
    cfg = OmegaConf.create(
        {
            "configurations": {"B": {"r": 1.0, "alpha": 10.0}, "D": {"r": 5.0, "alpha": 20.0}},
            "evaluation": {"fusion_ci": {"n_boot": 500, "seed": 0, "level": 0.95}},
        }
    )
    res = ab.collect_fusion_seeds(["seeds_1", "seeds_2"], cfg)
    saved = json.loads((repo / "reports" / "ablations" / "fusion_seeds.json").read_text())
    assert saved == json.loads(json.dumps(res))
    assert saved["seeds"] == ["default", "seeds_1", "seeds_2"]
    assert saved["commits"]["default"] == base and saved["n_boot"] == 500
    per_seed = saved["rows"]["D"]["dnn"]["kld_fou_mean"]["per_seed"]
    assert per_seed[1] - per_seed[0] == pytest.approx(-0.01)
    assert per_seed[2] - per_seed[0] == pytest.approx(-0.02)
    with pytest.raises(RuntimeError, match="no DVC experiment ablation-seeds_3"):
        ab.collect_fusion_seeds(["seeds_3"], cfg)
    # a replicate whose baseline holds another default run is refused
    other = commit(_samples(shift=0.5), "another default run")
    rev = commit(_samples(shift=-0.03), "seed 3")
    subprocess.run(
        ["git", "update-ref", "refs/exps/ab/cd/ablation-seeds_3", rev], cwd=repo, check=True
    )
    assert other != base
    with pytest.raises(RuntimeError, match="seed replicates on different default runs"):
        ab.collect_fusion_seeds(["seeds_1", "seeds_3"], cfg)
