"""Fusion data generated in shard ranges on several machines and merged: byte-identical to one
machine's run; overlapping, missing, out-of-bounds or mismatched parts fail with one line naming
the part or file, before anything is written.

Unit tests of :func:`traffictwin.io.shard_parts.merge_parts` on tiny synthetic shards (fast); stage
tests of ``python -m pipelines.generate_fusion --shards i:j`` / ``--merge`` on the ci profile
(``slow``: ~12 stage runs of a few seconds each).
"""

from __future__ import annotations

import json
import re
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import copy_repo, run, stage_in_process

from traffictwin.io.shard_parts import merge_parts
from traffictwin.io.shards import (
    MANIFEST,
    Dataset,
    DatasetError,
    DatasetWriter,
    part_name,
)

# ---------------------------------------------------------------------------------------------
# the library: merge_parts on synthetic shards

N = 5
PARAMS = {"n": N, "size": [2, 3]}
SPLITS = ["train", "train", "val", "test", "train"]


def _shard(i: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(i)
    return {"x": rng.random((2, 3), dtype=np.float32), "id": np.full(2, i)}


def _write(root: Path, indices: range, part: bool, params: dict = PARAMS) -> Path:
    w = DatasetWriter(root, "unit", params, seed=7)
    for i in indices:
        w.add_shard(i, _shard(i), split=SPLITS[i])
    extra = {"per_shard": 2}
    if part:
        w.finalize_part(indices.start, indices.stop, N, extra=extra, stats={"seconds": 1.0})
    else:
        w.finalize(extra=extra)
    return root


def E(path: Path) -> str:
    """``path`` as a literal in a regular expression."""
    return re.escape(str(path))


def _merge(sources: list[Path], dest: Path, params: dict = PARAMS) -> dict:
    manifest, _ = merge_parts(
        sources, dest, kind="unit", params=params, seed=7, n_shards=N, splits=SPLITS
    )
    return manifest


def _same_folder(a: Path, b: Path) -> None:
    names = sorted(p.name for p in a.iterdir())
    assert names == sorted(p.name for p in b.iterdir())
    for n in names:
        assert (a / n).read_bytes() == (b / n).read_bytes(), n


def test_merged_parts_are_byte_identical_to_one_writer(tmp_path: Path) -> None:
    whole = _write(tmp_path / "whole", range(N), part=False)
    p1 = _write(tmp_path / "p1", range(0, 2), part=True)
    p2 = _write(tmp_path / "p2", range(2, N), part=True)
    assert sorted(x.name for x in p1.iterdir()) == [
        part_name(0, 2),
        "shard-00000.npz",
        "shard-00001.npz",
    ]
    manifest = _merge([p2, p1], tmp_path / "merged")  # the order of the folders does not matter
    _same_folder(whole, tmp_path / "merged")
    assert manifest == json.loads((whole / MANIFEST).read_text())
    assert len(Dataset(tmp_path / "merged", kind="unit")) == 2 * N
    # into one part's own folder: its partial manifest goes, the other part's shards come
    _merge([p1, p2], p2)
    _same_folder(whole, p2)


def _parts(tmp_path: Path) -> tuple[Path, Path]:
    return _write(tmp_path / "p1", range(0, 2), True), _write(tmp_path / "p2", range(2, N), True)


def test_missing_and_overlapping_ranges_name_the_parts(tmp_path: Path) -> None:
    p1, p2 = _parts(tmp_path)
    dest = tmp_path / "out"
    with pytest.raises(DatasetError, match=r"shards 2\.\.4 of 5 are in no part"):
        _merge([p1], dest)
    p3 = _write(tmp_path / "p3", range(1, 3), True)
    with pytest.raises(
        DatasetError,
        match=r"p3/manifest.part-00001-00003.json \(shards 1:3\) overlaps .*p1/manifest.part-00000-00002.json in shards 1\.\.1",
    ):
        _merge([p1, p3, p2], dest)
    with pytest.raises(DatasetError, match=r"shards 0\.\.1 of 5 are in no part"):
        _merge([p2], dest)
    assert not dest.exists()


def test_bad_part_files_are_named(tmp_path: Path) -> None:
    p1, p2 = _parts(tmp_path)
    dest = tmp_path / "out"
    part = p2 / part_name(2, N)
    good = part.read_text()

    def edited(change) -> None:
        d = json.loads(good)
        change(d)
        part.write_text(json.dumps(d))

    edited(lambda d: d["part"].update(stop=9))
    with pytest.raises(DatasetError, match=rf"{E(part)}: shard range 2:9 out of bounds \(0:5\)"):
        _merge([p1, p2], dest)
    edited(lambda d: d["part"].update(n_shards=6))
    with pytest.raises(DatasetError, match=rf"{E(part)}: part of 6 shards, expected 5"):
        _merge([p1, p2], dest)
    edited(lambda d: d.update(seed=8))
    with pytest.raises(DatasetError, match=rf"{E(part)}: seed is 8, expected 7"):
        _merge([p1, p2], dest)
    edited(lambda d: d["shards"][0].update(split="test"))
    with pytest.raises(
        DatasetError, match=rf"{E(part)}: shard 2 is in split 'test', expected 'val'"
    ):
        _merge([p1, p2], dest)
    part.write_text("{")
    with pytest.raises(DatasetError, match=rf"{E(part)}: not valid JSON"):
        _merge([p1, p2], dest)
    part.write_text(good)
    shard = p2 / "shard-00003.npz"
    data = bytearray(shard.read_bytes())
    data[len(data) // 2] ^= 0xFF
    shard.write_bytes(bytes(data))
    with pytest.raises(DatasetError, match=rf"{E(shard)}: SHA-256 mismatch"):
        _merge([p1, p2], dest)
    shard.unlink()
    with pytest.raises(DatasetError, match=rf"{E(shard)}: listed in {E(part)} but missing"):
        _merge([p1, p2], dest)
    with pytest.raises(DatasetError, match=rf"{E(tmp_path / 'nope')}: folder not found"):
        _merge([p1, tmp_path / "nope"], dest)
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match=rf"{E(tmp_path / 'empty')}: no partial manifest"):
        _merge([p1, tmp_path / "empty"], dest)
    assert not dest.exists()


def test_parts_with_other_params_are_named_with_the_key(tmp_path: Path) -> None:
    p1 = _write(tmp_path / "p1", range(0, 2), True)
    p2 = _write(tmp_path / "p2", range(2, N), True, params={**PARAMS, "size": [2, 4]})
    with pytest.raises(
        DatasetError,
        match=rf"{E(p2 / part_name(2, N))}: generated with other parameters: 'size' is \[2, 4\] there, \[2, 3\] here",
    ):
        _merge([p1, p2], tmp_path / "out")


def test_a_part_needs_exactly_its_range(tmp_path: Path) -> None:
    w = DatasetWriter(tmp_path / "p", "unit", PARAMS, seed=7)
    w.add_shard(0, _shard(0), split="train")
    with pytest.raises(ValueError, match=r"part 0:2 needs shards 0\.\.1, written are \[0\]"):
        w.finalize_part(0, 2, N)
    with pytest.raises(ValueError, match=r"shard range 0:9 is not within 0:5"):
        w.finalize_part(0, 9, N)


# ---------------------------------------------------------------------------------------------
# the stage on the ci profile (5 shards of 4 pairs)

GEN = [sys.executable, "-m", "pipelines.generate_fusion"]


@pytest.fixture(scope="module")
def sharded(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A ci repo copy; ``full``: one machine's data/fusion, ``m1`` / ``m2``: the folders of
    ``--shards 0:2`` and ``--shards 2:5`` (each run in data/fusion, then moved away)."""
    base = tmp_path_factory.mktemp("sharded")
    repo = copy_repo(base / "repo")
    run([sys.executable, "-m", "pipelines.compose_params", "profile=ci"], repo)
    out = {"repo": repo}
    for name, extra in (("full", []), ("m1", ["--shards", "0:2"]), ("m2", ["--shards", "2:5"])):
        run([*GEN, *extra], repo)
        out[name] = base / name
        shutil.move(repo / "data" / "fusion", out[name])
    out["metrics_bytes"] = (repo / "reports/metrics/fusion_data.json").read_bytes()
    return out


@pytest.mark.slow
def test_stage_parts_merge_to_one_machines_data(sharded: dict[str, Path]) -> None:
    repo = sharded["repo"]
    assert sorted(p.name for p in sharded["m2"].iterdir()) == [
        part_name(2, 5),
        "shard-00002.npz",
        "shard-00003.npz",
        "shard-00004.npz",
    ]
    metrics = repo / "reports/metrics/fusion_data.json"
    metrics.unlink()
    run([*GEN, "--merge", str(sharded["m1"]), str(sharded["m2"])], repo)
    data = repo / "data" / "fusion"
    _same_folder(sharded["full"], data)  # every shard file and manifest.json
    assert metrics.read_bytes() == sharded["metrics_bytes"]  # no timings: the same file
    assert (
        json.loads((repo / "reports/timings/generate_fusion.json").read_text())["pairs_per_s"] > 0
    )
    # into the merging machine's own data/fusion (its part there, the other part copied in)
    shutil.rmtree(data)
    shutil.copytree(sharded["m2"], data)
    run([*GEN, "--merge", str(sharded["m1"]), "data/fusion"], repo)
    _same_folder(sharded["full"], data)
    shutil.rmtree(data)


def _fails(repo: Path, args: list[str], *expected: str) -> None:
    """The stage exits 2 with one line naming the problem and leaves no data/fusion (run in this
    process: ``tests/reliability/test_stage_errors.py`` checks the exit status of a stage process)."""
    code, err = stage_in_process(repo, "generate_fusion", args)
    assert code == 2, err[-2000:]
    line = err.strip().splitlines()[-1]
    assert line.startswith("generate_fusion: error: "), err[-2000:]
    for e in expected:
        assert e in line, (e, line)
    assert not (repo / "data" / "fusion").exists()


@pytest.mark.slow
def test_stage_refuses_bad_ranges_and_parts(sharded: dict[str, Path]) -> None:
    repo, m1, m2 = sharded["repo"], sharded["m1"], sharded["m2"]
    for bad in ("3:9", "2:2", "a:b", "3"):
        _fails(repo, ["--shards", bad], f"--shards {bad}")
    _fails(repo, ["--merge", str(m1)], "shards 2..4 of 5 are in no part")
    _fails(repo, ["--merge", str(m2)], "shards 0..1 of 5 are in no part")
    # an overlapping range from a third machine
    run([*GEN, "--shards", "1:3"], repo)
    m3 = repo.parent / "m3"
    shutil.move(repo / "data" / "fusion", m3)
    _fails(
        repo,
        ["--merge", str(m1), str(m3), str(m2)],
        f"{m3 / part_name(1, 3)} (shards 1:3) overlaps {m1 / part_name(0, 2)} in shards 1..1",
    )
    # a part generated with other params (another lidar range) than the merging machine's
    run(
        [
            sys.executable,
            "-m",
            "pipelines.compose_params",
            "profile=ci",
            "fusion_data.lidar.max_range=45",
        ],
        repo,
    )
    run([*GEN, "--shards", "2:5"], repo)
    m4 = repo.parent / "m4"
    shutil.move(repo / "data" / "fusion", m4)
    run([sys.executable, "-m", "pipelines.compose_params", "profile=ci"], repo)
    _fails(
        repo,
        ["--merge", str(m1), str(m4)],
        str(m4 / part_name(2, 5)),
        "'fusion_data.lidar.max_range' is 45 there, 50.0 here",
    )
    # a shard corrupted on its way between machines
    m5 = repo.parent / "m5"
    shutil.copytree(m2, m5)
    victim = m5 / "shard-00003.npz"
    data = bytearray(victim.read_bytes())
    data[len(data) // 2] ^= 0xFF
    victim.write_bytes(bytes(data))
    _fails(repo, ["--merge", str(m1), str(m5)], f"{victim}: SHA-256 mismatch")
