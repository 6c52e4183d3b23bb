"""Sharded datasets with a manifest (docs/design.md "Data").

A dataset folder holds ``manifest.json`` and shards ``shard-00000.npz`` ... Each shard is a
zip of ``.npy`` arrays written with fixed zip timestamps, so the same arrays give the
same bytes (deterministic generation is testable by hashing; :mod:`traffictwin.io.npz`). Shards and the manifest
are written atomically. Tables (poses, risk values, flags) are CSV files listed in the
manifest with their SHA-256 as well.

Reading verifies the manifest: schema version, kind, every shard's presence and hash.
Errors name the file and what is wrong. A shard or table name of the manifest must be a
relative path inside the dataset folder (:func:`check_member_name`: not absolute, no ``..``, no
folder that resolves outside it); anything else is refused before a file is opened. The last
component may be a symbolic link (DVC's ``symlink`` cache type links files into its cache).
:meth:`Dataset.load_all` compares every shard's array shapes (all dimensions but the first),
read from the ``.npy`` headers before any array is decompressed, with those of the dataset's
other shards, and names the shard that differs.

Shards hold finite numbers only (:func:`~traffictwin.io.npz.check_finite`): writers refuse float arrays with NaN or
±inf, and readers refuse them too (a shard with a valid hash may still come from an older or
foreign writer). Arrays where infinity is a defined value (e.g. "no object ahead" headways) are
named in ``allow_inf`` by the writer and the reader; NaN is never data.

A dataset can also be generated in parts on several machines: each writes a shard range and a
partial manifest (:meth:`DatasetWriter.finalize_part`); :func:`traffictwin.io.shard_parts.merge_parts` checks the parts
against each other and the expected parameters and writes the same ``manifest.json`` one machine
would have written.
"""

from __future__ import annotations

import json
from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from traffictwin.io.atomic import write_csv_atomic, write_json_atomic
from traffictwin.io.limits import InputError, npz_headers
from traffictwin.io.npz import DatasetError, read_npz, sha256_file, write_npz_deterministic

SCHEMA_VERSION = 1
MANIFEST = "manifest.json"


def shard_name(index: int) -> str:
    return f"shard-{index:05d}.npz"


def check_member_name(root: str | Path, name: Any, where: str | Path) -> Path:
    """The path of the manifest entry ``name`` inside the dataset folder ``root``.

    :class:`DatasetError` naming ``where`` (the manifest) and the name, before anything is
    opened, unless ``name`` is a non-empty relative path without ``..`` whose folders stay inside
    ``root`` once symbolic links are resolved (the file itself may be a link, as DVC makes them).
    """
    root = Path(root)
    bad = not isinstance(name, str) or not name or "\0" in name
    if not bad:
        parts = name.replace("\\", "/").split("/")
        bad = (
            name.startswith(("/", "\\"))
            or Path(name).is_absolute()
            or (len(name) > 1 and name[1] == ":")  # a Windows drive
            or any(part in ("..", "") for part in parts)
        )
    if not bad:
        top = root.resolve()
        parent = (root / name).parent.resolve()
        bad = parent != top and top not in parent.parents
    if bad:
        raise DatasetError(
            f"{where}: entry name {name!r} is not a relative path inside the dataset folder "
            f"{root} (absolute, '..' or outside it); refusing to open it"
        )
    return root / name


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
                try:
                    p = check_member_name(self.root, s.get("name"), self._progress)
                except DatasetError:
                    continue  # never a file outside the folder: that shard is written anew
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
        self,
        index: int,
        arrays: Mapping[str, np.ndarray],
        split: str | None = None,
        *,
        allow_inf: Collection[str] = (),
        check: bool = True,
    ) -> ShardInfo:
        """Write shard ``index`` (all arrays share the first dimension = sample count; finite,
        see :func:`write_npz_deterministic` for ``allow_inf`` and ``check``)."""
        counts = {k: len(v) for k, v in arrays.items()}
        if len(set(counts.values())) > 1:
            raise ValueError(f"shard {index}: arrays disagree on the sample count: {counts}")
        name = shard_name(index)
        digest = write_npz_deterministic(self.root / name, arrays, allow_inf=allow_inf, check=check)
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
        path = write_csv_atomic(self.root / name, frame, float_format="%.9g", lineterminator="\n")
        self._tables[name] = sha256_file(path)

    def finalize(self, extra: Mapping[str, Any] | None = None) -> dict[str, Any]:
        """Write ``manifest.json``; returns the manifest dict."""
        shards = [self._shards[i] for i in sorted(self._shards)]
        manifest = build_manifest(
            self.kind, self.seed, self.params, shards, sorted(self._tables.items()), extra
        )
        write_json_atomic(self.root / MANIFEST, manifest)
        if self._progress.exists():
            self._progress.unlink()
        return manifest

    def finalize_part(
        self,
        start: int,
        stop: int,
        n_shards: int,
        extra: Mapping[str, Any] | None = None,
        stats: Mapping[str, Any] | None = None,
    ) -> dict[str, Any]:
        """Write the partial manifest :func:`part_name` ``(start, stop)`` of shards
        ``start .. stop - 1`` out of ``n_shards`` (no ``manifest.json``: the folder is one part of a
        dataset generated on several machines; :func:`merge_parts` joins the parts). ``extra``
        goes into the final manifest, ``stats`` (e.g. seconds) only into the part. Returns it."""
        if not 0 <= start < stop <= n_shards:
            raise ValueError(f"shard range {start}:{stop} is not within 0:{n_shards}")
        if sorted(self._shards) != list(range(start, stop)):
            raise ValueError(
                f"{self.root}: part {start}:{stop} needs shards {start}..{stop - 1}, "
                f"written are {sorted(self._shards)}"
            )
        if self._tables:
            raise ValueError(
                f"{self.root}: tables {sorted(self._tables)} cannot be split into parts"
            )
        part = {
            **self._identity(),
            "part": {"start": int(start), "stop": int(stop), "n_shards": int(n_shards)},
            "shards": [
                {"index": i, "name": s.name, "sha256": s.sha256, "count": s.count, "split": s.split}
                for i, s in sorted(self._shards.items())
            ],
            "extra": json.loads(json.dumps(dict(extra or {}), sort_keys=True, default=str)),
            "stats": dict(stats or {}),
        }
        write_json_atomic(self.root / part_name(start, stop), part)
        if self._progress.exists():
            self._progress.unlink()
        return part


def build_manifest(
    kind: str,
    seed: int,
    params: Mapping[str, Any],
    shards: Sequence[ShardInfo],
    tables: Sequence[tuple[str, str]] = (),
    extra: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """The ``manifest.json`` dict of ``shards`` (in order) and ``tables`` (name, SHA-256)."""
    splits: dict[str, int] = {}
    for s in shards:
        if s.split is not None:
            splits[s.split] = splits.get(s.split, 0) + s.count
    return {
        "schema_version": SCHEMA_VERSION,
        "kind": kind,
        "seed": seed,
        "params": params,
        "count": sum(s.count for s in shards),
        "split_counts": splits,
        "shards": [
            {"name": s.name, "sha256": s.sha256, "count": s.count, "split": s.split} for s in shards
        ],
        "tables": [{"name": n, "sha256": d} for n, d in tables],
        **(dict(extra) if extra else {}),
    }


# ---------------------------------------------------------------------------------------------
# a dataset generated in parts (shard ranges) on several machines: the writer's side (the
# merge is traffictwin.io.shard_parts.merge_parts)

PART_GLOB = "manifest.part-*.json"


def part_name(start: int, stop: int) -> str:
    """File name of the partial manifest of shards ``start .. stop - 1``."""
    return f"manifest.part-{start:05d}-{stop:05d}.json"


class Dataset:
    """A verified, read-only view of a dataset folder."""

    def __init__(
        self,
        root: str | Path,
        kind: str | None = None,
        verify: bool = True,
        allow_inf: Collection[str] = (),
    ) -> None:
        """``allow_inf``: arrays where ±inf is a value (NaN never is; :func:`~traffictwin.io.npz.check_finite`)."""
        self.root = Path(root)
        self.allow_inf = tuple(allow_inf)
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
        for entry in [*self.manifest["shards"], *(self.manifest.get("tables") or [])]:
            if not isinstance(entry, dict) or "name" not in entry or "sha256" not in entry:
                raise DatasetError(f"{mpath}: entry {entry!r} lacks 'name' or 'sha256'")
            check_member_name(self.root, entry["name"], mpath)  # before any file is opened
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
        p = check_member_name(self.root, name, self.root / MANIFEST)
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

    def load_shard(self, i: int, keys: Iterable[str] | None = None) -> dict[str, np.ndarray]:
        """Shard ``i``'s arrays (only ``keys`` when given), its SHA-256 checked first."""
        s = self.shards[i]
        return read_npz(self._check(s["name"], s["sha256"]), self.allow_inf, keys)

    def iter_shards(
        self, split: str | None = None, keys: Iterable[str] | None = None
    ) -> Iterable[dict[str, np.ndarray]]:
        names = None if keys is None else list(keys)
        for i in self.shard_indices(split):
            yield self.load_shard(i, names)

    def _header_shapes(self, keys: list[str] | None) -> dict[int, dict[str, tuple[int, ...]]]:
        """Array shapes of every shard (index -> key -> shape) from its ``.npy`` headers, nothing
        decompressed; shards whose headers cannot be read are left out (loading them names why)."""
        out: dict[int, dict[str, tuple[int, ...]]] = {}
        for i, s in enumerate(self.shards):
            try:  # each header parsed under NPY_HEADER_LOCK (see traffictwin.io.npz._NPY_PARSE_LOCK)
                heads = npz_headers(self.root / s["name"], keys, max_bytes=None)
            except InputError:
                continue
            out[i] = {k: h.shape for k, h in heads.items() if h.shape}
        return out

    def check_shapes(self, idx: Iterable[int], keys: Iterable[str] | None = None) -> None:
        """:class:`DatasetError` naming the first shard of ``idx`` whose array (of ``keys``; all
        when ``None``) differs in its dimensions but the first from most of the dataset's shards
        (ties: the earliest shard's shape), or whose first dimension is not the manifest's
        ``count``. Read from the ``.npy`` headers of every shard, before any array is
        decompressed; a differing shard's SHA-256 is checked first, so a tampered one is named
        as such."""
        names = None if keys is None else list(keys)
        shapes = self._header_shapes(names)
        ref: dict[str, tuple[tuple[int, ...], list[int]]] = {}  # key -> (trailing dims, shards)
        for k in sorted({k for sh in shapes.values() for k in sh}):
            votes: dict[tuple[int, ...], list[int]] = {}
            for i, sh in shapes.items():  # in manifest order: the first shape wins a tie
                if k in sh:
                    votes.setdefault(sh[k][1:], []).append(i)
            trail, having = max(votes.items(), key=lambda kv: len(kv[1]))
            ref[k] = (trail, having)
        for i in idx:
            entry = self.shards[i]
            path = self.root / entry["name"]
            count = entry.get("count")
            for k, shape in sorted(shapes.get(i, {}).items()):
                trail, having = ref[k]
                if shape[1:] != trail:
                    self._check(entry["name"], entry["sha256"])
                    want = ", ".join(map(str, (shape[0], *trail)))
                    raise DatasetError(
                        f"{path}: array '{k}' has shape {shape}, expected ({want}) like "
                        f"{len(having)} of the dataset's {len(shapes)} shards (e.g. "
                        f"{self.shards[having[0]]['name']}); all dimensions but the first must agree"
                    )
                if isinstance(count, int) and shape[0] != count:
                    self._check(entry["name"], entry["sha256"])
                    raise DatasetError(
                        f"{path}: array '{k}' has shape {shape}: {shape[0]} samples, but "
                        f"{self.root / MANIFEST} lists {count} for this shard"
                    )

    def load_all(
        self,
        split: str | None = None,
        keys: Iterable[str] | None = None,
        *,
        check: Any = None,
        workers: int = 2,
    ) -> dict[str, np.ndarray]:
        """Every shard (of ``split``) concatenated; ``keys`` limits the arrays loaded (the others
        are never decompressed). ``check(name, arrays)``, if given, runs on each shard's arrays as
        it arrives (e.g. a mass check; raise to refuse the shard). Every shard's array shapes
        are checked against the dataset's other shards first (:meth:`check_shapes`, headers
        only), so a shard of another grid or image size is named. Shards are read, hashed and
        decompressed by ``workers`` threads (zlib and SHA-256 release the GIL) straight into the
        preallocated result, which is the same for any number of workers."""
        from concurrent.futures import ThreadPoolExecutor

        idx = self.shard_indices(split)
        if not idx:
            raise DatasetError(
                f"{self.root}: no shards" + (f" in split '{split}'" if split else "")
            )
        names = None if keys is None else list(keys)
        self.check_shapes(idx, names)  # from the headers: a differing shard named, none decoded
        first = self.load_shard(idx[0], names)
        names = list(first) if names is None else names
        counts = [len(first[names[0]])] + [int(self.shards[i]["count"]) for i in idx[1:]]
        starts = np.concatenate([[0], np.cumsum(counts)])
        out = {
            k: np.empty((int(starts[-1]), *first[k].shape[1:]), dtype=first[k].dtype) for k in names
        }

        def fill(j: int, arrays: dict[str, np.ndarray] | None = None) -> None:
            arrays = self.load_shard(idx[j], names) if arrays is None else arrays
            name = self.shards[idx[j]]["name"]
            for k in names:
                a = arrays[k]
                if len(a) != counts[j] or a.shape[1:] != out[k].shape[1:]:
                    raise DatasetError(
                        f"{self.root / name}: array '{k}' has shape {a.shape}, expected "
                        f"({counts[j]}, {', '.join(map(str, out[k].shape[1:]))}) like the other "
                        "shards and the manifest's count"
                    )
                out[k][starts[j] : starts[j + 1]] = a
            if check is not None:
                check(name, arrays)

        fill(0, first)
        del first
        if len(idx) > 1:
            with ThreadPoolExecutor(max(1, min(workers, len(idx) - 1))) as pool:
                list(pool.map(fill, range(1, len(idx))))
        return out

    def table(self, name: str) -> Any:
        import pandas as pd

        entry = next((t for t in self.manifest.get("tables", []) if t["name"] == name), None)
        if entry is None:
            raise DatasetError(f"{self.root / MANIFEST}: no table '{name}'")
        return pd.read_csv(self._check(name, entry["sha256"]))


def derived_dataset(
    root: str | Path, kind: str, source: Dataset, source_label: str, stage: str
) -> Dataset:
    """The dataset at ``root`` (not re-verified) that a stage derived from ``source``: its
    manifest's ``params.source`` must be ``source``'s manifest hash. ``source_label`` names the
    source and ``stage`` the stage that writes ``root`` in the errors (a clear
    :class:`DatasetError` when ``root`` has no manifest or was made from other data)."""
    root = Path(root)
    if not (root / MANIFEST).exists():
        raise DatasetError(f"{root}: no {MANIFEST} (run `dvc repro {stage}` first)")
    derived = Dataset(root, kind=kind, verify=False)
    made_from, expected = derived.params.get("source"), source.manifest_hash()
    if made_from != expected:
        raise DatasetError(
            f"{root / MANIFEST}: made from another {source_label} (source {made_from}, "
            f"{source_label} is {expected}): run the {stage} stage first"
        )
    return derived
