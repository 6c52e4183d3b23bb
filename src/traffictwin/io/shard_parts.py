"""A dataset generated in parts (shard ranges) on several machines, joined into one.

Each machine writes a shard range and a partial manifest (:meth:`DatasetWriter.finalize_part`,
named by :func:`~traffictwin.io.shards.part_name`); :func:`merge_parts` checks the parts
against each other and the expected parameters and writes the same ``manifest.json`` one machine
would have written.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from traffictwin.io.atomic import atomic_path, write_json_atomic
from traffictwin.io.npz import DatasetError, sha256_file
from traffictwin.io.shards import (
    MANIFEST,
    PART_GLOB,
    SCHEMA_VERSION,
    ShardInfo,
    build_manifest,
    shard_name,
)
from traffictwin.nested import lookup


def _first_difference(a: Any, b: Any, key: str = "") -> str | None:
    """Dotted key of the first place where ``a`` and ``b`` differ (``None`` when equal)."""
    if isinstance(a, Mapping) and isinstance(b, Mapping):
        for k in sorted(set(a) | set(b)):
            sub = f"{key}.{k}" if key else str(k)
            if k not in a or k not in b:
                return sub
            d = _first_difference(a[k], b[k], sub)
            if d is not None:
                return d
        return None
    return None if a == b else (key or "<root>")


def _read_part(path: Path) -> dict[str, Any]:
    try:
        part = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise DatasetError(f"{path}: not valid JSON ({exc})") from None
    for key in ("schema_version", "kind", "seed", "params", "part", "shards", "extra"):
        if key not in part:
            raise DatasetError(f"{path}: field '{key}' missing (not a partial manifest)")
    for key in ("start", "stop", "n_shards"):
        if not isinstance(part["part"].get(key), int):
            raise DatasetError(f"{path}: field 'part.{key}' missing or not an integer")
    return part


_Part = tuple[Path, Path, dict[str, Any]]  # (folder, part file, partial manifest)


def _collect_parts(sources: Sequence[str | Path]) -> list[_Part]:
    """Every partial manifest in the folders ``sources``, in folder and file-name order."""
    parts: list[_Part] = []
    for src in map(Path, sources):
        if not src.is_dir():
            raise DatasetError(f"{src}: folder not found (expected a part's output folder)")
        files = sorted(src.glob(PART_GLOB))
        if not files:
            raise DatasetError(
                f"{src}: no partial manifest ({PART_GLOB}); generate a part there with --shards i:j"
            )
        parts += [(src, f, _read_part(f)) for f in files]
    return parts


def _check_part(
    f: Path, part: dict[str, Any], want: dict[str, Any], first: _Part, n_shards: int
) -> None:
    """:class:`DatasetError` naming part file ``f`` unless it was generated with ``want``'s
    schema, kind, seed and params, the ``first`` part's extras, for ``n_shards`` shards, and
    lists exactly the shards of its range."""
    for key in ("schema_version", "kind", "seed"):
        if part[key] != want[key]:
            raise DatasetError(f"{f}: {key} is {part[key]!r}, expected {want[key]!r}")
    params = want["params"]
    diff = _first_difference(part["params"], params)
    if diff is not None:
        raise DatasetError(
            f"{f}: generated with other parameters: '{diff}' is "
            f"{lookup(part['params'], diff, '<missing>')!r} there, "
            f"{lookup(params, diff, '<missing>')!r} here"
        )
    extra0 = first[2]["extra"]
    if part["extra"] != extra0:
        raise DatasetError(
            f"{f}: manifest extras {part['extra']} differ from {first[1]}'s {extra0}"
        )
    r = part["part"]
    if r["n_shards"] != n_shards:
        raise DatasetError(f"{f}: part of {r['n_shards']} shards, expected {n_shards}")
    if not 0 <= r["start"] < r["stop"] <= n_shards:
        raise DatasetError(
            f"{f}: shard range {r['start']}:{r['stop']} out of bounds (0:{n_shards})"
        )
    listed = [s.get("index") for s in part["shards"]]
    if listed != list(range(r["start"], r["stop"])):
        raise DatasetError(f"{f}: lists shards {listed}, expected {r['start']}..{r['stop'] - 1}")


def _check_coverage(parts: list[_Part], n_shards: int) -> None:
    """:class:`DatasetError` unless the parts (sorted by range) cover ``0 .. n_shards - 1``
    exactly once, naming the overlapping part or the missing shards."""
    covered = 0
    prev: Path | None = None
    for _src, f, part in parts:
        start, stop = part["part"]["start"], part["part"]["stop"]
        if start < covered:
            raise DatasetError(
                f"{f} (shards {start}:{stop}) overlaps {prev} in shards {start}..{min(stop, covered) - 1}"
            )
        if start > covered:
            raise DatasetError(
                f"shards {covered}..{start - 1} of {n_shards} are in no part "
                f"(parts: {', '.join(str(p[1]) for p in parts)})"
            )
        covered, prev = stop, f
    if covered < n_shards:
        raise DatasetError(
            f"shards {covered}..{n_shards - 1} of {n_shards} are in no part "
            f"(parts: {', '.join(str(p[1]) for p in parts)})"
        )


def _verified_shards(
    parts: list[_Part], splits: Sequence[str] | None
) -> list[tuple[Path, ShardInfo]]:
    """Each part's shard files with their records, in shard order: named as the writer names
    them, in split ``splits[i]`` (when given), present, and matching their SHA-256."""
    infos: list[tuple[Path, ShardInfo]] = []
    for src, f, part in parts:
        for s in part["shards"]:
            i = int(s["index"])
            if s["name"] != shard_name(i):
                raise DatasetError(
                    f"{f}: shard {i} is named {s['name']!r}, expected {shard_name(i)!r}"
                )
            if splits is not None and s.get("split") != splits[i]:
                raise DatasetError(
                    f"{f}: shard {i} is in split {s.get('split')!r}, expected {splits[i]!r}"
                )
            path = src / s["name"]
            if not path.exists():
                raise DatasetError(f"{path}: listed in {f} but missing")
            got = sha256_file(path)
            if got != s["sha256"]:
                raise DatasetError(
                    f"{path}: SHA-256 mismatch ({f.name} {s['sha256'][:12]}…, file {got[:12]}…): "
                    "corrupt or tampered"
                )
            infos.append((path, ShardInfo(s["name"], s["sha256"], int(s["count"]), s.get("split"))))
    return infos


def _write_merged(
    dest: Path, infos: list[tuple[Path, ShardInfo]], manifest: dict[str, Any]
) -> None:
    """Copy the shards into ``dest`` (verified), write ``manifest`` last, then remove every
    other file there (partial manifests, stale shards)."""
    dest.mkdir(parents=True, exist_ok=True)
    (dest / MANIFEST).unlink(missing_ok=True)
    for path, info in infos:
        target = dest / info.name
        if target.exists() and target.resolve() == path.resolve():
            continue
        with atomic_path(target, suffix=".npz") as tmp:
            shutil.copyfile(path, tmp)
            if sha256_file(tmp) != info.sha256:
                raise DatasetError(f"{path}: changed while it was copied to {target}")
    write_json_atomic(dest / MANIFEST, manifest)
    keep = {MANIFEST, *(i.name for _, i in infos)}
    for p in dest.iterdir():
        if p.is_file() and p.name not in keep:
            p.unlink()


def merge_parts(
    sources: Sequence[str | Path],
    dest: str | Path,
    *,
    kind: str,
    params: Mapping[str, Any],
    seed: int,
    n_shards: int,
    splits: Sequence[str] | None = None,
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Join the parts in the folders ``sources`` (each with one or more
    :func:`~traffictwin.io.shards.part_name` files and their shards) into the dataset folder
    ``dest``: shards copied (verified by SHA-256), ``manifest.json`` written exactly as one
    machine's :meth:`DatasetWriter.finalize` would, and every other file in ``dest`` (partial
    manifests, stale shards) removed. ``dest`` may be one of ``sources``.

    Every part must have been generated with ``kind``, ``seed`` and ``params`` (as the writer
    records them), for ``n_shards`` shards, and (when given) shard ``i`` must be in split
    ``splits[i]``; the parts' ranges must cover ``0 .. n_shards - 1`` exactly once. All of this
    is checked before anything is written; :class:`DatasetError` names the part or file.
    Returns the manifest and the parts (their ``stats`` included), in shard order.
    """
    params = json.loads(json.dumps(params, sort_keys=True, default=str))
    want = {"schema_version": SCHEMA_VERSION, "kind": kind, "seed": int(seed), "params": params}
    parts = _collect_parts(sources)
    extra0 = parts[0][2]["extra"]  # the first part found (in folder order) is the reference
    for _src, f, part in parts:
        _check_part(f, part, want, parts[0], n_shards)
    parts.sort(key=lambda p: (p[2]["part"]["start"], p[2]["part"]["stop"]))
    _check_coverage(parts, n_shards)
    infos = _verified_shards(parts, splits)
    # everything checked: write dest (shards first, the manifest last, then drop the rest)
    manifest = build_manifest(kind, int(seed), params, [i for _, i in infos], (), extra0)
    _write_merged(Path(dest), infos, manifest)
    return manifest, [p for _, _, p in parts]
