"""Sharded datasets with a manifest (DESIGN.md "Data").

A dataset folder holds ``manifest.json`` and shards ``shard-00000.npz`` ... Each shard is a
zip of ``.npy`` arrays written with fixed zip timestamps, so the same arrays give the
same bytes (deterministic generation is testable by hashing). Shards and the manifest
are written atomically. Tables (poses, risk values, flags) are CSV files listed in the
manifest with their SHA-256 as well.

Reading verifies the manifest: schema version, kind, every shard's presence and hash.
Errors name the file and what is wrong.
"""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from traffictwin.io.atomic import atomic_path, write_json_atomic

SCHEMA_VERSION = 1
MANIFEST = "manifest.json"
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)


class DatasetError(RuntimeError):
    """A dataset folder, manifest, shard or table is missing, corrupt or of the wrong kind."""


def shard_name(index: int) -> str:
    return f"shard-{index:05d}.npz"


def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while True:
            b = fh.read(chunk)
            if not b:
                break
            h.update(b)
    return h.hexdigest()


def write_npz_deterministic(
    path: str | Path, arrays: Mapping[str, np.ndarray], compresslevel: int = 6
) -> str:
    """Write ``arrays`` as a compressed ``.npz`` with fixed metadata, atomically; return its SHA-256."""
    path = Path(path)
    with atomic_path(path, suffix=".npz") as tmp:
        with zipfile.ZipFile(
            tmp, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=compresslevel
        ) as zf:
            for key in sorted(arrays):
                buf = io.BytesIO()
                np.lib.format.write_array(
                    buf, np.ascontiguousarray(arrays[key]), allow_pickle=False
                )
                info = zipfile.ZipInfo(f"{key}.npy", date_time=_ZIP_DATE)
                info.compress_type = zipfile.ZIP_DEFLATED
                info.external_attr = 0o644 << 16
                zf.writestr(
                    info,
                    buf.getvalue(),
                    compress_type=zipfile.ZIP_DEFLATED,
                    compresslevel=compresslevel,
                )
        digest = sha256_file(tmp)
    return digest


def read_npz(path: str | Path) -> dict[str, np.ndarray]:
    """Read every array of an ``.npz`` into memory; a clear error if it is not a readable archive."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise DatasetError(f"{path}: file not found") from None
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as exc:
        raise DatasetError(f"{path}: not a readable .npz archive ({exc})") from None


@dataclass
class ShardInfo:
    name: str
    sha256: str
    count: int
    split: str | None = None


class DatasetWriter:
    """Writes shards into ``root`` and, on :meth:`finalize`, the manifest.

    ``kind`` names the dataset type (e.g. ``"fusion"``, ``"prealigned"``, ``"risk"``);
    ``params`` are the parameters that produced it (recorded verbatim, and used to decide
    whether already written shards can be reused when a stage resumes).
    """

    def __init__(self, root: str | Path, kind: str, params: Mapping[str, Any], seed: int) -> None:
        self.root = Path(root)
        self.kind = kind
        self.params = json.loads(json.dumps(params, sort_keys=True, default=str))
        self.seed = int(seed)
        self.root.mkdir(parents=True, exist_ok=True)
        self._progress = self.root / ".progress.json"
        self._shards: dict[int, ShardInfo] = {}
        self._tables: dict[str, str] = {}
        self._resume_state()

    # -- resume -------------------------------------------------------------------------------
    def _identity(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "params": self.params,
            "seed": self.seed,
            "schema_version": SCHEMA_VERSION,
        }

    def _resume_state(self) -> None:
        """Keep shards of an interrupted run with the same identity; wipe anything else."""
        prev = None
        if self._progress.exists():
            try:
                prev = json.loads(self._progress.read_text())
            except json.JSONDecodeError:
                prev = None
        if prev is not None and prev.get("identity") == self._identity():
            for s in prev.get("shards", []):
                p = self.root / s["name"]
                if p.exists() and sha256_file(p) == s["sha256"]:
                    self._shards[int(s["index"])] = ShardInfo(
                        s["name"], s["sha256"], s["count"], s.get("split")
                    )
        # anything in the folder that is not a kept shard belongs to another run
        keep = {s.name for s in self._shards.values()}
        for p in self.root.iterdir():
            if p.is_file() and p.name not in keep and p.name != self._progress.name:
                p.unlink()
        self._save_progress()

    def _save_progress(self) -> None:
        write_json_atomic(
            self._progress,
            {
                "identity": self._identity(),
                "shards": [
                    {
                        "index": i,
                        "name": s.name,
                        "sha256": s.sha256,
                        "count": s.count,
                        "split": s.split,
                    }
                    for i, s in sorted(self._shards.items())
                ],
            },
        )

    def has_shard(self, index: int) -> bool:
        """True when shard ``index`` was already written by an identical earlier run."""
        return index in self._shards

    # -- writing ------------------------------------------------------------------------------
    def add_shard(
        self, index: int, arrays: Mapping[str, np.ndarray], split: str | None = None
    ) -> ShardInfo:
        """Write shard ``index`` (all arrays share the first dimension = sample count)."""
        counts = {k: len(v) for k, v in arrays.items()}
        if len(set(counts.values())) > 1:
            raise ValueError(f"shard {index}: arrays disagree on the sample count: {counts}")
        name = shard_name(index)
        digest = write_npz_deterministic(self.root / name, arrays)
        return self.record_shard(
            index, name, digest, next(iter(counts.values())) if counts else 0, split
        )

    def record_shard(
        self, index: int, name: str, sha256: str, count: int, split: str | None = None
    ) -> ShardInfo:
        """Record a shard written elsewhere (e.g. by a worker process) under ``root/name``."""
        info = ShardInfo(name, sha256, int(count), split)
        self._shards[index] = info
        self._save_progress()
        return info

    def add_table(self, name: str, frame: Any) -> None:
        """Write a pandas DataFrame as CSV ``name`` (atomically) and list it in the manifest."""
        path = self.root / name
        with atomic_path(path, suffix=".csv") as tmp:
            frame.to_csv(tmp, index=False, float_format="%.9g", lineterminator="\n")
            digest = sha256_file(tmp)
        self._tables[name] = digest

    def finalize(self, extra: Mapping[str, Any] | None = None) -> dict[str, Any]:
        """Write ``manifest.json``; returns the manifest dict."""
        shards = [self._shards[i] for i in sorted(self._shards)]
        splits: dict[str, int] = {}
        for s in shards:
            if s.split is not None:
                splits[s.split] = splits.get(s.split, 0) + s.count
        manifest = {
            "schema_version": SCHEMA_VERSION,
            "kind": self.kind,
            "seed": self.seed,
            "params": self.params,
            "count": sum(s.count for s in shards),
            "split_counts": splits,
            "shards": [
                {"name": s.name, "sha256": s.sha256, "count": s.count, "split": s.split}
                for s in shards
            ],
            "tables": [{"name": n, "sha256": d} for n, d in sorted(self._tables.items())],
            **(dict(extra) if extra else {}),
        }
        write_json_atomic(self.root / MANIFEST, manifest)
        if self._progress.exists():
            self._progress.unlink()
        return manifest


class Dataset:
    """A verified, read-only view of a dataset folder."""

    def __init__(self, root: str | Path, kind: str | None = None, verify: bool = True) -> None:
        self.root = Path(root)
        mpath = self.root / MANIFEST
        if not self.root.is_dir():
            raise DatasetError(
                f"{self.root}: dataset folder not found (run the stage that writes it first)"
            )
        if not mpath.exists():
            raise DatasetError(f"{mpath}: manifest missing (the dataset was not finalised)")
        try:
            self.manifest: dict[str, Any] = json.loads(mpath.read_text())
        except json.JSONDecodeError as exc:
            raise DatasetError(f"{mpath}: not valid JSON ({exc})") from None
        for key in ("schema_version", "kind", "shards", "count"):
            if key not in self.manifest:
                raise DatasetError(f"{mpath}: field '{key}' missing")
        if self.manifest["schema_version"] != SCHEMA_VERSION:
            raise DatasetError(
                f"{mpath}: schema_version {self.manifest['schema_version']} (expected {SCHEMA_VERSION})"
            )
        if kind is not None and self.manifest["kind"] != kind:
            raise DatasetError(f"{mpath}: kind '{self.manifest['kind']}' (expected '{kind}')")
        self._verified: set[str] = set()
        if verify:
            self.verify()

    @property
    def shards(self) -> list[dict[str, Any]]:
        return self.manifest["shards"]

    @property
    def params(self) -> dict[str, Any]:
        return self.manifest.get("params", {})

    def __len__(self) -> int:
        return int(self.manifest["count"])

    def manifest_hash(self) -> str:
        """SHA-256 of manifest.json: one string that identifies this data version."""
        return sha256_file(self.root / MANIFEST)

    def _check(self, name: str, expected: str) -> Path:
        p = self.root / name
        if not p.exists():
            raise DatasetError(f"{p}: listed in {self.root / MANIFEST} but missing")
        if name not in self._verified:
            got = sha256_file(p)
            if got != expected:
                raise DatasetError(
                    f"{p}: SHA-256 mismatch (manifest {expected[:12]}…, file {got[:12]}…): corrupt or tampered"
                )
            self._verified.add(name)
        return p

    def verify(self) -> None:
        """Check every shard and table against the manifest's hashes."""
        for s in self.shards:
            self._check(s["name"], s["sha256"])
        for t in self.manifest.get("tables", []):
            self._check(t["name"], t["sha256"])

    def shard_indices(self, split: str | None = None) -> list[int]:
        return [i for i, s in enumerate(self.shards) if split is None or s.get("split") == split]

    def load_shard(self, i: int) -> dict[str, np.ndarray]:
        s = self.shards[i]
        return read_npz(self._check(s["name"], s["sha256"]))

    def iter_shards(self, split: str | None = None) -> Iterable[dict[str, np.ndarray]]:
        for i in self.shard_indices(split):
            yield self.load_shard(i)

    def load_all(
        self, split: str | None = None, keys: Iterable[str] | None = None
    ) -> dict[str, np.ndarray]:
        """Concatenate every shard (of ``split``); ``keys`` limits the arrays loaded."""
        parts = list(self.iter_shards(split))
        if not parts:
            raise DatasetError(
                f"{self.root}: no shards" + (f" in split '{split}'" if split else "")
            )
        names = list(keys) if keys is not None else list(parts[0])
        for k in names:
            if k not in parts[0]:
                raise DatasetError(
                    f"{self.root / self.shards[0]['name']}: array '{k}' missing (has {sorted(parts[0])})"
                )
        return {k: np.concatenate([p[k] for p in parts]) for k in names}

    def table(self, name: str) -> Any:
        import pandas as pd

        entry = next((t for t in self.manifest.get("tables", []) if t["name"] == name), None)
        if entry is None:
            raise DatasetError(f"{self.root / MANIFEST}: no table '{name}'")
        return pd.read_csv(self._check(name, entry["sha256"]))
