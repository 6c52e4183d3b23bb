"""A manifest's shard and table names stay inside
the dataset folder, and a shard of the wrong shape is named.

Before: a manifest shard name ``../../../etc/passwd`` was opened and hashed (only the SHA-256
mismatch refused it); a wrong-shape shard whose hash was updated in the manifest made
``train_fusion`` fail in NumPy ("all the input array dimensions ... must match") without naming
the shard.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from traffictwin.io import shards as sh
from traffictwin.io.shards import Dataset, DatasetError, DatasetWriter


def _arrays(seed: int, n: int = 3, size: int = 16) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    x = (rng.random((n, 4, size, size), dtype=np.float32) / 2).astype(np.float32)
    return {"inputs": x, "label": np.ascontiguousarray(x[:, :2]), "id": np.arange(n) + 10 * seed}


def _dataset(root: Path, sizes=(16, 16, 16, 16), splits=("train", "train", "train", "val")) -> Path:
    w = DatasetWriter(root, "prealigned", {"unit": 1}, seed=0)
    for i, (size, split) in enumerate(zip(sizes, splits, strict=True)):
        w.add_shard(i, _arrays(i, size=size), split=split)
    w.add_table("frames.csv", pd.DataFrame({"a": [1, 2]}))
    w.finalize()
    return root


def _edit_manifest(root: Path, edit) -> None:
    path = root / sh.MANIFEST
    m = json.loads(path.read_text())
    edit(m)
    path.write_text(json.dumps(m))


def _one_line(exc: BaseException, *needles: str) -> str:
    text = str(exc)
    assert "\n" not in text, text
    for n in needles:
        assert n in text, text
    return text


# ------------------------------------------------------------------ names stay inside


@pytest.mark.parametrize(
    "name",
    [
        "../../../etc/passwd",
        "/etc/passwd",
        "sub/../../outside.npz",
        "..",
        "",
        "C:\\Windows\\win.ini",
        "..\\outside.npz",
        42,
    ],
)
@pytest.mark.parametrize("entry", ["shards", "tables"])
def test_a_name_outside_the_dataset_is_refused_before_it_is_opened(
    tmp_path, monkeypatch, name, entry
):
    root = _dataset(tmp_path / "ds")
    _edit_manifest(root, lambda m: m[entry][0].__setitem__("name", name))
    opened: list[str] = []
    monkeypatch.setattr(sh, "sha256_file", lambda p, *a: opened.append(str(p)) or "0" * 64)
    for verify in (True, False):
        with pytest.raises(DatasetError) as info:
            Dataset(root, verify=verify)
        _one_line(info.value, str(root / sh.MANIFEST), repr(name), "refusing to open it")
    assert opened == []


def test_a_linked_folder_leading_outside_is_refused(tmp_path):
    root = _dataset(tmp_path / "ds")
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    (outside / "shard-00000.npz").write_bytes((root / "shard-00000.npz").read_bytes())
    os.symlink(outside, root / "linked")
    _edit_manifest(root, lambda m: m["shards"][0].__setitem__("name", "linked/shard-00000.npz"))
    with pytest.raises(DatasetError) as info:
        Dataset(root)
    _one_line(info.value, "'linked/shard-00000.npz'", "outside")


def test_a_linked_file_and_a_subfolder_stay_readable(tmp_path):
    """DVC's symlink cache type links each file into the cache: the file may be a link."""
    root = _dataset(tmp_path / "ds")
    cache = tmp_path / "cache"
    cache.mkdir()
    (root / "shard-00001.npz").rename(cache / "abc")
    os.symlink(cache / "abc", root / "shard-00001.npz")
    (root / "part").mkdir()
    (root / "shard-00002.npz").rename(root / "part" / "shard-00002.npz")
    _edit_manifest(root, lambda m: m["shards"][2].__setitem__("name", "part/shard-00002.npz"))
    ds = Dataset(root)
    assert ds.load_all("train")["inputs"].shape == (9, 4, 16, 16)
    assert ds.table("frames.csv")["a"].tolist() == [1, 2]


def test_direct_reads_check_the_name_too(tmp_path):
    root = _dataset(tmp_path / "ds")
    ds = Dataset(root)
    ds.manifest["shards"][1]["name"] = "../ds/../../x.npz"  # changed after the constructor
    with pytest.raises(DatasetError, match="refusing to open it"):
        ds.load_shard(1)
    with pytest.raises(DatasetError, match="refusing to open it"):
        sh.check_member_name(root, "/abs.npz", "here")
    assert sh.check_member_name(root, "shard-00000.npz", "here") == root / "shard-00000.npz"


def test_resume_never_touches_a_file_outside_the_folder(tmp_path):
    root = tmp_path / "ds"
    victim = tmp_path / "victim.npz"
    victim.write_bytes(b"keep me")
    w = DatasetWriter(root, "prealigned", {"unit": 1}, seed=0)
    w.add_shard(0, _arrays(0))
    progress = json.loads((root / ".progress.json").read_text())
    progress["shards"].append(
        {"index": 1, "name": "../victim.npz", "sha256": sh.sha256_file(victim), "count": 3}
    )
    (root / ".progress.json").write_text(json.dumps(progress))
    w2 = DatasetWriter(root, "prealigned", {"unit": 1}, seed=0)
    assert w2.has_shard(0) and not w2.has_shard(1)
    assert victim.read_bytes() == b"keep me"


# ------------------------------------------------------------------ shapes named


@pytest.mark.parametrize("wrong", [0, 2, 3])
def test_a_wrong_shape_shard_is_named_with_key_shape_and_expected_shape(tmp_path, wrong):
    """Shard ``wrong`` (the first, a middle one, or the only shard of its split) has 32 x 32
    maps while the others have 16 x 16; its hash is the manifest's."""
    sizes = [32 if i == wrong else 16 for i in range(4)]
    root = _dataset(tmp_path / "ds", sizes=tuple(sizes))
    ds = Dataset(root)  # every hash matches
    split = "val" if wrong == 3 else "train"
    with pytest.raises(DatasetError) as info:
        ds.load_all(split, keys=["inputs", "label"])
    name = str(root / sh.shard_name(wrong))
    _one_line(
        info.value,
        f"{name}: array 'inputs' has shape (3, 4, 32, 32)",
        "expected (3, 4, 16, 16)",
        "like 3 of the dataset's 4 shards",
    )
    other = "train" if split == "val" else "val"
    assert ds.load_all(other, keys=["label"])["label"].shape[1:] == (2, 16, 16)


def test_a_shard_disagreeing_with_the_manifest_count_is_named(tmp_path):
    root = _dataset(tmp_path / "ds")
    _edit_manifest(root, lambda m: m["shards"][1].__setitem__("count", 5))
    with pytest.raises(DatasetError) as info:
        Dataset(root).load_all("train")
    _one_line(info.value, "shard-00001.npz", "3 samples", "lists 5")


def test_a_tampered_wrong_shape_shard_is_named_as_tampered(tmp_path):
    root = _dataset(tmp_path / "ds")
    sh.write_npz_deterministic(root / "shard-00002.npz", _arrays(2, size=32))  # hash not updated
    with pytest.raises(DatasetError) as info:
        Dataset(root, verify=False).load_all("train")
    _one_line(info.value, "shard-00002.npz", "SHA-256 mismatch")


def test_training_data_loader_names_the_shard(tmp_path):
    """What train_fusion reads: :func:`traffictwin.fusion.training_data.load_prealigned`."""
    from traffictwin.fusion.training_data import load_prealigned

    root = _dataset(tmp_path / "D", sizes=(16, 16, 16, 32))
    x, y = load_prealigned(root, "train")
    assert x.shape == (9, 4, 16, 16) and y.shape == (9, 2, 16, 16)
    with pytest.raises(DatasetError) as info:
        load_prealigned(root, "val")
    _one_line(info.value, "shard-00003.npz", "'inputs'", "(3, 4, 32, 32)", "(3, 4, 16, 16)")
