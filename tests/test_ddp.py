"""DDP on CPU (gloo, 2 ranks): both networks train through their real DVC stages, rank zero alone
publishes, one MLflow run each, and validation over 2 ranks equals validation in one process.

The sampler unit tests (:class:`~traffictwin.trainer.RankShardSampler`) are fast; the stage
tests are ``slow`` (a copy of the shared ci DAG, two DDP trainings, eight validation runs: ~2 min
on 2 cores).
"""

from __future__ import annotations

import itertools
import json
import sqlite3
import sys
from pathlib import Path

import pytest
import torch
from conftest import copy_dag, run, stage_env
from torch.utils.data import RandomSampler, SequentialSampler

from traffictwin.trainer import RankShardSampler

# ---------------------------------------------------------------------------------------------
# the sampler (no process group needed)


def _batches(base, world: int, block: int) -> list[list[int]]:
    """Each rank's batches of ``block`` (a DataLoader over its share), all ranks together."""
    out = []
    for r in range(world):
        share = list(RankShardSampler(base, world, r, even=False, block=block))
        assert len(share) == len(RankShardSampler(base, world, r, even=False, block=block))
        assert share, f"rank {r} got nothing"
        out += [share[i : i + block] for i in range(0, len(share), block)]
    return out


def test_evaluation_shares_are_one_process_batches_each_once() -> None:
    """Every index on exactly one rank; with at least one batch per rank, the ranks' batches are
    exactly one process's batches (same composition, so the same float32 sums per batch)."""
    for n in (2, 3, 7, 8, 9):
        for world in (2, 3):
            for block in (1, 2, 4, 64):
                if n < world:
                    continue
                got = _batches(SequentialSampler(range(n)), world, block)
                assert sorted(i for b in got for i in b) == list(range(n)), (n, world, block)
                single = [list(range(i, min(i + block, n))) for i in range(0, n, block)]
                if len(single) >= world:
                    assert sorted(got) == single, (n, world, block)


def test_training_shares_split_one_draw_evenly_per_epoch() -> None:
    """Every rank draws the same k of n (a seeded RandomSampler); the ranks take disjoint, equal
    shares of it, and the next epoch is a fresh draw — k pairs per epoch in all, not n per rank."""
    n, k, world = 12, 7, 2

    def sampler() -> RandomSampler:
        g = torch.Generator().manual_seed(5)
        return RandomSampler(range(n), replacement=False, num_samples=k, generator=g)

    ranks = [RankShardSampler(sampler(), world, r, even=True) for r in range(world)]
    single = sampler()
    for _epoch in range(3):
        draw = list(single)
        parts = [list(s) for s in ranks]
        assert [len(p) for p in parts] == [k // world] * world == [len(s) for s in ranks]
        assert not set(parts[0]) & set(parts[1])
        assert sorted(parts[0] + parts[1]) == sorted(draw[: k - k % world])


def test_evaluation_set_smaller_than_the_world_is_refused() -> None:
    with pytest.raises(ValueError, match="1 evaluation sample.* 2 ranks"):
        RankShardSampler(SequentialSampler(range(1)), 2, 0, even=False)


# ---------------------------------------------------------------------------------------------
# the stages under DDP

DDP = [
    "profile=ci",
    "trainer=ddp",
    "trainer.accelerator=cpu",
    "trainer.devices=2",
    "trainer.precision=32-true",  # the ddp group's bf16-mixed is for GPUs
    "trainer.num_workers=0",
    # 8 of the 12 ci training pairs per epoch in batches of 2: 2 steps per rank and epoch when the
    # ranks share the draw (3 if each rank took half of all pairs, the DistributedSampler default)
    "fusion_model.train.train_samples_per_epoch=8",
    "fusion_model.train.batch_size=2",
]
STAGES = ("train_fusion", "train_risk@headline")
PUBLISHED = {
    "models/fusion/network/model.ckpt",
    "models/fusion/network/model_meta.json",
    "reports/metrics/train_fusion_network.json",
    "reports/plots/train_fusion_network.csv",
    "reports/timings/train_fusion.json",
    "models/risk/headline/model.ckpt",
    "models/risk/headline/model_meta.json",
    "models/risk/headline/history.csv",
    "reports/plots/risk_training_headline.csv",
    "reports/timings/train_risk-headline.json",
}
TOL = {"rel": 1e-5, "abs": 1e-8}
_RUNS = itertools.count()


def _files(repo: Path) -> set[str]:
    """Every file of the copy outside git/DVC internals, the MLflow store and Python's bytecode
    caches (``__pycache__``, written by any import where bytecode writing is on)."""
    skip = (".git/", ".dvc/", "mlartifacts/")
    return {
        p.relative_to(repo).as_posix()
        for p in repo.rglob("*")
        if p.is_file()
        and not p.relative_to(repo).as_posix().startswith(skip)
        and "__pycache__" not in p.parts
    }


@pytest.fixture(scope="module")
def ddp_repo(ci_dag: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A copy of the finished ci DAG (its data and DVC cache: nothing is generated again, and a
    store of its own: the only MLflow runs are the DDP trainings'), the two training stages'
    outputs removed, then both stages run by `dvc repro` with the DDP trainer; returns the copy,
    the files the training added and its log."""
    repo = copy_dag(ci_dag, tmp_path_factory.mktemp("ddp") / "repo", mlflow=False)
    for rel in PUBLISHED:
        (repo / rel).unlink(missing_ok=True)
    run([sys.executable, "-m", "pipelines.compose_params", *DDP], repo)
    before = _files(repo)
    proc = run(["dvc", "repro", *STAGES], repo, timeout=1200)
    return {
        "repo": repo,
        "new": _files(repo) - before,
        "log": proc.stdout + proc.stderr,
    }


def _validate(repo: Path, problem: str, devices: int, *args: str) -> list[dict]:
    """tests/ddp_validate.py in the copy: per ``--subset``, val/* metrics and samples_seen over
    all ranks."""
    out = repo / f"val-{problem}-{devices}-{next(_RUNS)}.json"
    env = stage_env(repo)
    env["OMP_WAIT_POLICY"] = "PASSIVE"
    run(
        [
            sys.executable,
            "tests/ddp_validate.py",
            problem,
            "--devices",
            str(devices),
            "--out",
            str(out),
            *args,
        ],
        repo,
        env=env,
        timeout=600,
    )
    res = json.loads(out.read_text())
    out.unlink()
    return res


@pytest.mark.slow
@pytest.mark.xdist_group("ddp_repo")  # one worker builds the module's repo once
def test_ddp_stages_publish_once_from_rank_zero(ddp_repo: dict) -> None:
    repo = ddp_repo["repo"]
    new = {f for f in ddp_repo["new"] if not f.endswith(".gitignore")} - {"mlflow.db"}
    assert new == PUBLISHED, f"stray: {sorted(new - PUBLISHED)}, missing: {sorted(PUBLISHED - new)}"
    log = ddp_repo["log"]
    assert "GLOBAL_RANK: 1, MEMBER: 2/2" in log, "the stages did not run on 2 ranks"
    assert log.count("train_fusion: best epoch") == 1
    assert log.count("train_risk@headline: best val MSE") == 1
    out = run(["dvc", "status", *STAGES], repo).stdout
    assert "up to date" in out.lower(), out


@pytest.mark.slow
@pytest.mark.xdist_group("ddp_repo")  # one worker builds the module's repo once
def test_ddp_fusion_epoch_draws_train_samples_per_epoch_in_all(ddp_repo: dict) -> None:
    """8 pairs per epoch shared by 2 ranks in batches of 2: 2 optimiser steps per epoch."""
    repo = ddp_repo["repo"]
    ck = torch.load(repo / "models/fusion/network/model.ckpt", weights_only=True)
    assert ck["global_step"] == (ck["epoch"] + 1) * 8 // (2 * 2)
    assert "data_root" not in ck["traffictwin"]  # no absolute path in a DVC output


@pytest.mark.slow
@pytest.mark.xdist_group("ddp_repo")  # one worker builds the module's repo once
def test_ddp_stages_log_one_mlflow_run_each(ddp_repo: dict) -> None:
    repo = ddp_repo["repo"]
    with sqlite3.connect(repo / "mlflow.db") as db:
        rows = db.execute(
            "SELECT e.name, r.name, r.status, r.run_uuid FROM runs r "
            "JOIN experiments e ON e.experiment_id = r.experiment_id"
        ).fetchall()
    # a run's name: the stage's run name, then in brackets what differs from the committed
    # params.yaml (here the DDP trainer)
    base = {r[3]: r[1].split(" [")[0] for r in rows}
    with sqlite3.connect(repo / "mlflow.db") as db:
        params = dict(
            db.execute(
                "SELECT key, value FROM params WHERE run_uuid = ?",
                (next(u for u, n in base.items() if n == "fusion-network"),),
            ).fetchall()
        )
    assert sorted((r[0], base[r[3]], r[2]) for r in rows) == [
        ("fusion", "fusion-network", "FINISHED"),
        ("risk", "risk-headline", "FINISHED"),
    ]
    assert params["trainer.strategy"] == "ddp" and params["trainer.devices"] == "2"
    for record in (
        "reports/timings/train_fusion.json",
        "reports/timings/train_risk-headline.json",
    ):
        run_id = json.loads((repo / record).read_text())["run_id"]  # the rank-zero run record
        assert run_id in {r[3] for r in rows}, record


def _assert_same(single: dict, ddp: dict, n: int) -> None:
    assert single["world_size"] == 1 and ddp["world_size"] == 2
    assert single["samples_seen"] == ddp["samples_seen"] == n, "a sample was left out or repeated"
    keys = sorted(k for k in single if k.startswith("val/"))
    assert keys and keys == sorted(k for k in ddp if k.startswith("val/"))
    for k in keys:
        assert ddp[k] == pytest.approx(single[k], **TOL), k


@pytest.mark.slow
@pytest.mark.xdist_group("ddp_repo")  # one worker builds the module's repo once
def test_ddp_fusion_validation_equals_one_process(ddp_repo: dict) -> None:
    repo = ddp_repo["repo"]
    model = ["--model", "models/fusion/network", "--data", "data/prealigned/mixed"]
    n_val = json.loads((repo / "data/prealigned/mixed/manifest.json").read_text())["split_counts"][
        "val"
    ]
    assert n_val == 4  # the ci profile's validation split
    # the whole validation split (0: all 4 pairs) in batches of 2: one batch per rank; then 3
    # pairs in batches of 1: the ranks get 2 and 1 (Lightning's DistributedSampler would repeat one)
    subsets = ["--subset", "0:2", "--subset", "3:1"]
    singles = _validate(repo, "fusion", 1, *model, *subsets)
    ddps = _validate(repo, "fusion", 2, *model, *subsets)
    for one, two, n in zip(singles, ddps, (n_val, 3), strict=True):
        _assert_same(one, two, n)
    # what the stage computed on 2 ranks during training for the kept epoch (val_samples 8 >= 4
    # pairs, batches of 2) is one process's validation of the published weights
    stage = json.loads((repo / "reports/metrics/train_fusion_network.json").read_text())
    assert stage["val_pairs"] == n_val
    for k in ("val/loss", "val/kld", "val/kld_full", "val/dice_free", "val/dice_occ"):
        assert stage[k] == pytest.approx(singles[0][k], **TOL), k


@pytest.mark.slow
@pytest.mark.xdist_group("ddp_repo")  # one worker builds the module's repo once
def test_ddp_risk_validation_equals_one_process(ddp_repo: dict) -> None:
    repo = ddp_repo["repo"]
    model = ["--model", "models/risk/headline", "--repo", "."]
    meta = json.loads((repo / "models/risk/headline/model_meta.json").read_text())
    n_val = meta["n_val"]
    assert n_val == 4  # the ci profile's validation frames
    subsets = ["--subset", "0:2", "--subset", "3:1"]  # all 4 frames in batches of 2; 3 in 1s
    singles = _validate(repo, "risk", 1, *model, *subsets)
    ddps = _validate(repo, "risk", 2, *model, *subsets)
    for one, two, n in zip(singles, ddps, (n_val, 3), strict=True):
        _assert_same(one, two, n)
    # the kept checkpoint's validation MSE, computed on 2 ranks during training
    assert meta["best_val_mse"] == pytest.approx(singles[0]["val/mse"], **TOL)
