"""Sharded dataset I/O: deterministic bytes, manifest verification, resume, atomicity."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from traffictwin.io.atomic import atomic_path, write_json_atomic
from traffictwin.io.shards import (
    Dataset,
    DatasetError,
    DatasetWriter,
    derived_dataset,
    read_npz,
    write_npz_deterministic,
)


def _arrays(seed: int, n: int = 3) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {"x": rng.random((n, 2, 8, 8), dtype=np.float32), "id": np.arange(n, dtype=np.int64)}


def _write(root: Path, seed: int = 0) -> dict:
    w = DatasetWriter(root, "unit", {"n": 3}, seed=seed)
    w.add_shard(0, _arrays(0), split="train")
    w.add_shard(1, _arrays(1), split="test")
    w.add_table("frames.csv", pd.DataFrame({"a": [1, 2], "b": [0.5, 0.25]}))
    return w.finalize()


def test_same_arrays_give_identical_bytes(tmp_path: Path) -> None:
    a = write_npz_deterministic(tmp_path / "a.npz", _arrays(3))
    b = write_npz_deterministic(tmp_path / "b.npz", _arrays(3))
    assert a == b
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
    got = read_npz(tmp_path / "a.npz")
    np.testing.assert_array_equal(got["x"], _arrays(3)["x"])


def test_arrays_with_meta_round_trip_deterministically(tmp_path: Path) -> None:
    from traffictwin.io.figure_inputs import read_arrays_with_meta, write_arrays_with_meta

    meta = {"sequence": 7, "method": "learned+network", "radius_m": 5.0}
    a = write_arrays_with_meta(tmp_path / "a.npz", _arrays(1), meta)
    b = write_arrays_with_meta(tmp_path / "b.npz", _arrays(1), dict(reversed(meta.items())))
    assert a == b  # key order of the metadata does not change the bytes
    arrays, got = read_arrays_with_meta(tmp_path / "a.npz")
    assert got == meta and set(arrays) == {"x", "id"}
    np.testing.assert_array_equal(arrays["id"], [0, 1, 2])
    write_npz_deterministic(tmp_path / "plain.npz", _arrays(1))
    with pytest.raises(DatasetError, match="plain.npz: no 'meta_json' array"):
        read_arrays_with_meta(tmp_path / "plain.npz")
    with pytest.raises(ValueError):  # NaN is no JSON: refused before anything is written
        write_arrays_with_meta(tmp_path / "nan.npz", _arrays(1), {"x": float("nan")})
    assert not (tmp_path / "nan.npz").exists()


def test_round_trip_and_splits(tmp_path: Path) -> None:
    m = _write(tmp_path / "ds")
    assert m["count"] == 6 and m["split_counts"] == {"train": 3, "test": 3}
    ds = Dataset(tmp_path / "ds", kind="unit")
    assert len(ds) == 6
    assert ds.shard_indices("test") == [1]
    allx = ds.load_all(keys=["x"])["x"]
    assert allx.shape == (6, 2, 8, 8)
    assert ds.table("frames.csv")["b"].tolist() == [0.5, 0.25]
    assert len(ds.manifest_hash()) == 64


def test_tampered_shard_is_named(tmp_path: Path) -> None:
    _write(tmp_path / "ds")
    p = tmp_path / "ds" / "shard-00001.npz"
    data = bytearray(p.read_bytes())
    data[-10] ^= 0xFF
    p.write_bytes(bytes(data))
    with pytest.raises(DatasetError, match=r"shard-00001\.npz.*SHA-256 mismatch"):
        Dataset(tmp_path / "ds")


def test_missing_shard_and_manifest(tmp_path: Path) -> None:
    _write(tmp_path / "ds")
    (tmp_path / "ds" / "shard-00000.npz").unlink()
    with pytest.raises(DatasetError, match=r"shard-00000\.npz.*missing"):
        Dataset(tmp_path / "ds")
    (tmp_path / "ds" / "manifest.json").unlink()
    with pytest.raises(DatasetError, match="manifest missing"):
        Dataset(tmp_path / "ds")
    with pytest.raises(DatasetError, match="not found"):
        Dataset(tmp_path / "nope")


def test_wrong_kind_and_schema(tmp_path: Path) -> None:
    _write(tmp_path / "ds")
    with pytest.raises(DatasetError, match="kind 'unit'.*expected 'risk'"):
        Dataset(tmp_path / "ds", kind="risk")
    mp = tmp_path / "ds" / "manifest.json"
    m = json.loads(mp.read_text())
    m["schema_version"] = 99
    mp.write_text(json.dumps(m))
    with pytest.raises(DatasetError, match="schema_version 99"):
        Dataset(tmp_path / "ds")


def test_truncated_npz_gives_clear_error(tmp_path: Path) -> None:
    write_npz_deterministic(tmp_path / "a.npz", _arrays(0))
    data = (tmp_path / "a.npz").read_bytes()
    (tmp_path / "a.npz").write_bytes(data[: len(data) // 2])
    with pytest.raises(DatasetError, match=r"a\.npz: not a readable"):
        read_npz(tmp_path / "a.npz")


def test_resume_keeps_identical_shards_and_wipes_foreign_ones(tmp_path: Path) -> None:
    root = tmp_path / "ds"
    w = DatasetWriter(root, "unit", {"n": 3}, seed=0)
    w.add_shard(0, _arrays(0), split="train")
    (root / "stray.tmp").write_text("junk")  # e.g. a killed writer's leftovers
    # an interrupted run: no finalize; restart with the same identity keeps shard 0
    w2 = DatasetWriter(root, "unit", {"n": 3}, seed=0)
    assert w2.has_shard(0) and not w2.has_shard(1)
    assert not (root / "stray.tmp").exists()
    # different params: nothing is reused
    w3 = DatasetWriter(root, "unit", {"n": 4}, seed=0)
    assert not w3.has_shard(0)
    assert not (root / "shard-00000.npz").exists()


def test_shard_count_mismatch_rejected(tmp_path: Path) -> None:
    w = DatasetWriter(tmp_path / "ds", "unit", {}, seed=0)
    with pytest.raises(ValueError, match="disagree on the sample count"):
        w.add_shard(0, {"a": np.zeros(2), "b": np.zeros(3)})


def test_atomic_write_leaves_old_file_on_error(tmp_path: Path) -> None:
    p = tmp_path / "out.json"
    write_json_atomic(p, {"good": 1})
    with pytest.raises(RuntimeError):
        with atomic_path(p) as tmp:
            tmp.write_text("half")
            raise RuntimeError("killed")
    assert json.loads(p.read_text()) == {"good": 1}
    assert [q.name for q in tmp_path.iterdir()] == ["out.json"]


def test_atomic_write_gives_the_usual_file_mode(tmp_path: Path) -> None:
    import os

    p = tmp_path / "m.json"
    write_json_atomic(p, {"a": 1})
    mask = os.umask(0)
    os.umask(mask)
    assert (p.stat().st_mode & 0o777) == (0o666 & ~mask)


def test_load_all_in_threads_equals_one_by_one_and_checks_each_shard(tmp_path: Path) -> None:
    w = DatasetWriter(tmp_path / "ds", "unit", {"n": 3}, seed=0)
    for i in range(7):
        w.add_shard(i, _arrays(i, n=2 + i % 3), split="train")
    w.finalize()
    ds = Dataset(tmp_path / "ds", kind="unit", verify=False)
    seen: list[str] = []
    got = ds.load_all("train", keys=["x", "id"], workers=2, check=lambda n, a: seen.append(n))
    want = [_arrays(i, n=2 + i % 3) for i in range(7)]
    np.testing.assert_array_equal(got["x"], np.concatenate([a["x"] for a in want]))
    np.testing.assert_array_equal(got["id"], np.concatenate([a["id"] for a in want]))
    assert sorted(seen) == [f"shard-{i:05d}.npz" for i in range(7)]  # every shard checked once
    one = Dataset(tmp_path / "ds", kind="unit").load_all("train", keys=["x"], workers=1)
    np.testing.assert_array_equal(one["x"], got["x"])
    # only the keys asked for; a missing key names the shard
    assert set(ds.load_all("train", keys=["id"])) == {"id"}
    with pytest.raises(DatasetError, match=r"shard-00000\.npz: array\(s\) \['y'\] missing"):
        ds.load_all("train", keys=["y"])

    # a check that refuses a shard stops the load with its error
    def refuse(name: str, a: dict) -> None:
        if name == "shard-00004.npz":
            raise DatasetError(f"{name}: bad masses")

    with pytest.raises(DatasetError, match="shard-00004.npz: bad masses"):
        ds.load_all("train", keys=["x"], check=refuse)


def test_threads_parse_npy_headers_one_at_a_time(tmp_path: Path, monkeypatch) -> None:
    """numpy parses .npy headers with ast.literal_eval, which CPython 3.11 cannot run in two
    threads at once (SystemError: AST constructor recursion depth mismatch): every array of a
    threaded load is parsed under the module's lock, never two at once."""
    import threading
    import time

    import traffictwin.io.npz as npz

    class Spy:
        def __init__(self) -> None:
            self.lock, self.inside, self.most, self.entries = threading.Lock(), 0, 0, 0

        def __enter__(self) -> None:
            self.lock.acquire()
            self.inside += 1
            self.entries += 1
            self.most = max(self.most, self.inside)
            time.sleep(0.001)  # widen the window a second thread would need

        def __exit__(self, *exc: object) -> None:
            self.inside -= 1
            self.lock.release()

    spy = Spy()
    monkeypatch.setattr(npz, "_NPY_PARSE_LOCK", spy)
    w = DatasetWriter(tmp_path / "ds", "unit", {"n": 3}, seed=0)
    for i in range(9):
        w.add_shard(i, _arrays(i), split="train")
    w.finalize()
    got = Dataset(tmp_path / "ds", kind="unit").load_all("train", keys=["x", "id"], workers=4)
    assert spy.entries == 9 * 2 and spy.most == 1  # each array of each shard, one at a time
    np.testing.assert_array_equal(got["id"], np.concatenate([_arrays(i)["id"] for i in range(9)]))


def test_load_all_refuses_a_shard_of_another_shape_and_a_tampered_one(tmp_path: Path) -> None:
    w = DatasetWriter(tmp_path / "ds", "unit", {"n": 3}, seed=0)
    w.add_shard(0, _arrays(0), split="train")
    odd = _arrays(1)
    odd["x"] = odd["x"][:, :, :4]  # (3, 2, 4, 8): another grid
    w.add_shard(1, odd, split="train")
    w.finalize()
    ds = Dataset(tmp_path / "ds", kind="unit", verify=False)
    with pytest.raises(
        DatasetError,
        match=r"shard-00001\.npz: array 'x' has shape \(3, 2, 4, 8\), expected \(3, 2, 8, 8\)",
    ):
        ds.load_all("train", keys=["x"])
    p = tmp_path / "ds" / "shard-00001.npz"
    data = bytearray(p.read_bytes())
    data[-10] ^= 0xFF
    p.write_bytes(bytes(data))
    with pytest.raises(DatasetError, match=r"shard-00001\.npz.*SHA-256 mismatch"):
        Dataset(tmp_path / "ds", kind="unit", verify=False).load_all("train", keys=["id"])


def test_derived_dataset_checks_its_source_and_names_the_stage(tmp_path: Path) -> None:
    _write(tmp_path / "src", seed=0)
    _write(tmp_path / "other", seed=1)
    source, other = Dataset(tmp_path / "src"), Dataset(tmp_path / "other")
    w = DatasetWriter(tmp_path / "derived", "unit", {"source": source.manifest_hash()}, seed=0)
    w.add_shard(0, _arrays(0), split="train")
    w.finalize()
    derived = derived_dataset(tmp_path / "derived", "unit", source, "data/src", "derive")
    assert derived.params["source"] == source.manifest_hash()
    with pytest.raises(DatasetError, match=r"made from another data/src .*run the derive stage"):
        derived_dataset(tmp_path / "derived", "unit", other, "data/src", "derive")
    with pytest.raises(DatasetError, match=r"no manifest.json \(run `dvc repro derive` first\)"):
        derived_dataset(tmp_path / "none", "unit", source, "data/src", "derive")
    with pytest.raises(DatasetError, match="kind 'unit' \\(expected 'disparity'\\)"):
        derived_dataset(tmp_path / "derived", "disparity", source, "data/src", "derive")
