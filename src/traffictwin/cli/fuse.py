"""``traffictwin fuse``: two evidential grid maps fused by the fusion network (MAP1 MAP2 with
their poses), or many pairs in one call (``--pairs LIST.csv|FOLDER``, batched inference)."""

from __future__ import annotations

import argparse
import csv
import io
import json
import sys
import time
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from traffictwin.api import DIVISOR, ApiWarning
from traffictwin.io.jsonio import json_clean
from traffictwin.io.outputs import OutputSet

from .common import (
    CliError,
    add_arguments,
    arg,
    csv_value,
    model_options,
    npz_png,
    output_options,
    parse_pose,
    png_bytes,
    positive_cell,
)
from .previews import preview_image

HELP = "fuse two evidential grid maps (or many pairs) with the fusion network"
DESCRIPTION = (
    "Prealign MAP2 into MAP1's frame by the poses and fuse them with the network; "
    "--pairs fuses many pairs in one call with batched inference."
)
ARGUMENTS = [
    arg("map1", nargs="?", default=None, help=".npz with m_free, m_occ (H, W) masses, ego map"),
    arg("map2", nargs="?", default=None, help=".npz of the other vehicle's map, same size"),
    arg("--pose1", default=None, help="x,y,yaw of map 1's sensor in the world (m, m, rad)"),
    arg("--pose2", default=None, help="x,y,yaw of map 2's sensor in the world (m, m, rad)"),
    arg(
        "--pairs",
        default=None,
        help="a CSV list (map1,map2[,id,x1,y1,yaw1,x2,y2,yaw2,cell]) or a folder of <id>_1.npz/<id>_2.npz",
    ),
    *model_options("fusion model", "traffictwin-fusion"),
    arg(
        "--cell",
        type=float,
        default=None,
        help="m per cell (default: the .npz 'cell', else the model's)",
    ),
    arg(
        "--batch-size", type=int, default=8, help="pairs per forward pass with --pairs (default 8)"
    ),
    arg("--no-preview", dest="preview", action="store_false", help="with --pairs: no PNG per pair"),
    *output_options(
        "output base name: writes OUT.npz and OUT.png (with --pairs: an output folder)"
    ),
]


def add_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("fuse", help=HELP, description=DESCRIPTION)
    add_arguments(p, ARGUMENTS)
    p.set_defaults(func=cmd_fuse)


def _write_fused(
    outs: OutputSet,
    path: Path,
    res: Any,
    pose1: np.ndarray,
    pose2: np.ndarray,
    preview: Path | None = None,
) -> None:
    """The fused ``.npz`` (deterministic zip, fast deflate level 1) into ``outs``' temp file of
    ``path``, and the PNG preview (:func:`preview_image`) into that of ``preview`` if given."""
    from traffictwin.io.shards import write_npz_deterministic

    arrays = {
        "m_free": res.masses[0],
        "m_occ": res.masses[1],
        "u": res.u,
        "pose1": np.asarray(pose1, np.float64),
        "pose2": np.asarray(pose2, np.float64),
        "rel_pose": np.asarray(res.rel_pose, np.float64),
        "cell": np.float64(res.cell),
    }
    write_npz_deterministic(outs.temp_path(path), arrays, compresslevel=1)
    if preview is not None:
        image = preview_image(res.m1, res.m2_prealigned, res.masses, res.u, cell=res.cell)
        outs.write_bytes(preview, png_bytes(image))


def _occupied(res: Any) -> int:
    return int(((res.masses[1] + res.u / 2) > 0.5).sum())


# ============================================================================ one pair


def cmd_fuse(args: argparse.Namespace) -> int:
    from traffictwin import api

    positive_cell(args.cell)
    if args.batch_size < 1:
        raise CliError(f"--batch-size: must be >= 1, got {args.batch_size}")
    if args.pairs is not None:
        return _fuse_many(args)
    if args.map1 is None or args.map2 is None:
        raise CliError("pass MAP1 MAP2 (with --pose1/--pose2) or --pairs LIST.csv|FOLDER")
    m1, c1, p1 = api.load_masses(args.map1)
    m2, c2, p2 = api.load_masses(args.map2)
    pose1 = parse_pose(args.pose1, "--pose1") if args.pose1 is not None else p1
    pose2 = parse_pose(args.pose2, "--pose2") if args.pose2 is not None else p2
    for opt, pose, path in (("--pose1", pose1, args.map1), ("--pose2", pose2, args.map2)):
        if pose is None:
            raise CliError(f"{opt}: required (x,y,yaw in m, m, rad): {path} has no 'pose'")
    if m1.shape != m2.shape:
        raise CliError(
            f"{args.map2}: grid size {m2.shape[1:]} differs from {args.map1}'s {m1.shape[1:]} (rows, cols)"
        )
    h, w = m1.shape[1:]
    if h % DIVISOR or w % DIVISOR:
        raise CliError(
            f"{args.map1}: grid {h}x{w} cells: rows and cols must be divisible by {DIVISOR} (network output stride)"
        )
    api.check_relative_pose(pose1, pose2, "--pose1, --pose2")
    if c1 is not None and c2 is not None and abs(c1 - c2) > 1e-9:
        raise CliError(f"{args.map2}: cell size {c2} m differs from {args.map1}'s {c1} m")
    own = c1 if c1 is not None else c2
    if args.cell is not None and own is not None and abs(args.cell - own) > 1e-9:
        raise CliError(f"--cell: {args.cell} m contradicts the maps' own cell size {own} m")
    npz_path, png_path = npz_png(args.output)
    with OutputSet([npz_path, png_path], inputs=[args.map1, args.map2], force=args.force) as outs:
        model = api.load_fusion(args.model, tracking_uri=args.tracking_uri)
        cell = args.cell if args.cell is not None else c1 if c1 is not None else c2
        cell = api.check_fusion_domain(model, (h, w), cell, str(args.map1))
        t0 = time.perf_counter()
        with warnings.catch_warnings():  # the API's warning names a pair id; this one the files
            warnings.simplefilter("ignore", ApiWarning)
            (res,) = api.fuse(model, [api.FusePair(m1, m2, pose1, pose2, cell, "pair")])
        ms = (time.perf_counter() - t0) * 1e3
        _write_fused(outs, npz_path, res, pose1, pose2, png_path)
        outs.commit()
    summary = {
        "output": str(npz_path),
        "preview": str(png_path),
        "model": model.description,
        "grid": [h, w],
        "cell_m": res.cell,
        "rel_pose": [float(v) for v in res.rel_pose],
        "fuse_ms": round(ms, 2),
        "mean_u": float(res.u.mean()),
        "occupied_cells": _occupied(res),
        "overlap": res.overlap,
    }
    if not res.overlap:
        print(
            f"traffictwin fuse: warning: {args.map2} does not overlap {args.map1}'s grid at "
            f"--pose1/--pose2 (map 2 at x {res.rel_pose[0]:.6g} m, y {res.rel_pose[1]:.6g} m in "
            "map 1's frame): the output is map 1 alone",
            file=sys.stderr,
        )
    print(json.dumps(json_clean(summary), indent=2))
    return 0


# ============================================================================ the list of pairs

_POSE_COLS = ("x1", "y1", "yaw1", "x2", "y2", "yaw2")


def _number(text: str | None) -> bool:
    """Whether a CSV field is empty/absent (allowed for optional columns) or a real number."""
    if text is None or not text.strip():
        return True
    try:
        float(text)
    except ValueError:
        return False
    return True


def read_pair_list(source: str | Path) -> list[dict[str, Any]]:
    """The pairs of ``fuse --pairs``: ``[{id, map1, map2, pose1|None, pose2|None, cell|None}]``
    from a CSV list or a folder of ``<id>_1.npz`` / ``<id>_2.npz`` (module doc). Checks the
    files exist and the ids are unique file names; reads no map."""
    src = Path(source)
    if src.is_dir():
        rows = _pairs_in_folder(src)
    elif src.is_file():
        rows = _pairs_in_csv(src)
    else:
        raise CliError(f"--pairs: {src}: no such list file or folder")
    seen: set[str] = set()
    for r in rows:
        if not r["id"] or "/" in r["id"] or r["id"] in (".", "..") or r["id"] in seen:
            raise CliError(
                f"--pairs: {src}: pair id {r['id']!r} is empty, repeated or not a file name"
            )
        seen.add(r["id"])
        for key in ("map1", "map2"):
            if not Path(r[key]).is_file():
                raise CliError(f"--pairs: {r[key]}: file not found (pair {r['id']!r})")
    return rows


def _pairs_in_folder(src: Path) -> list[dict[str, Any]]:
    ones = {p.name[: -len("_1.npz")]: p for p in sorted(src.glob("*_1.npz"))}
    twos = {p.name[: -len("_2.npz")]: p for p in sorted(src.glob("*_2.npz"))}
    lonely = sorted(set(ones) ^ set(twos))
    if lonely:
        raise CliError(
            f"--pairs: {src}: map '{lonely[0]}_1.npz' or '{lonely[0]}_2.npz' has no partner"
        )
    if not ones:
        raise CliError(f"--pairs: {src}: no pairs found (expected <id>_1.npz / <id>_2.npz)")
    return [
        {"id": k, "map1": ones[k], "map2": twos[k], "pose1": None, "pose2": None, "cell": None}
        for k in sorted(ones)
    ]


def _pairs_in_csv(src: Path) -> list[dict[str, Any]]:
    try:
        with open(src, newline="", encoding="utf-8-sig") as fh:  # a byte-order mark is no column
            table = list(csv.DictReader(fh))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise CliError(f"--pairs: {src}: not a readable CSV ({exc})") from None
    if not table:
        raise CliError(
            f"--pairs: {src}: no rows (expected columns map1,map2[,id,x1,y1,yaw1,x2,y2,yaw2,cell])"
        )
    cols = set(table[0])
    if not {"map1", "map2"} <= cols:
        raise CliError(f"--pairs: {src}: columns map1 and map2 are required (has {sorted(cols)})")
    has_pose = [c in cols for c in _POSE_COLS]
    if any(has_pose) and not all(has_pose):
        raise CliError(
            f"--pairs: {src}: pose columns must be all of {', '.join(_POSE_COLS)} or none"
        )
    header = list(table[0])
    return [_csv_pair(src, k, r, header, all(has_pose)) for k, r in enumerate(table, start=2)]


def _csv_pair(
    src: Path, k: int, r: dict[str | None, Any], header: list[str], with_pose: bool
) -> dict[str, Any]:
    """Line ``k`` of the list ``src``, checked: every field there, map names, numbers."""
    if None in r or any(v is None for v in r.values()):
        n = len([v for v in r.values() if v is not None]) + len(r.get(None) or [])
        raise CliError(
            f"--pairs: {src} line {k}: {n} field(s), but the header has {len(header)} "
            f"({','.join(header)})"
        )
    empty = [c for c in ("map1", "map2") if not r[c].strip()]
    if empty:
        raise CliError(f"--pairs: {src} line {k}: column {empty[0]} is empty (a .npz file)")
    pose_cols = _POSE_COLS if with_pose else ()
    bad = [c for c in pose_cols if not (r[c].strip() and _number(r[c]))]
    bad += [] if _number(r.get("cell")) else ["cell"]
    if bad:
        raise CliError(f"--pairs: {src} line {k}: column {bad[0]} = {r[bad[0]]!r} is not a number")
    pose = [float(r[c]) for c in _POSE_COLS] if with_pose else None
    cell = float(r["cell"]) if r.get("cell") not in (None, "") else None
    if pose is not None and not np.all(np.isfinite(pose)):
        raise CliError(f"--pairs: {src} line {k}: pose values must be finite")
    if cell is not None and not (cell > 0 and np.isfinite(cell)):
        raise CliError(
            f"--pairs: {src} line {k}: column cell = {r['cell']!r} must be a positive number of metres"
        )
    return {
        "id": (r.get("id") or f"{k - 1:05d}").strip(),
        "map1": src.parent / r["map1"],
        "map2": src.parent / r["map2"],
        "pose1": None if pose is None else np.array(pose[:3]),
        "pose2": None if pose is None else np.array(pose[3:]),
        "cell": cell,
    }


# ============================================================================ many pairs


def _fuse_many(args: argparse.Namespace) -> int:
    from traffictwin import api

    if args.map1 is not None:
        raise CliError("--pairs: pass either MAP1 MAP2 or --pairs, not both")
    if args.pose1 is not None or args.pose2 is not None:
        raise CliError(
            "--pairs: poses come from the list (x1..yaw2) or the maps' 'pose', not --pose1/--pose2"
        )
    rows = read_pair_list(args.pairs)
    if not args.output:
        raise CliError("-o: the output folder name is empty; expected a folder")
    out = Path(args.output)
    if out.exists() and not out.is_dir():
        raise CliError(f"-o: {out} is a file; with --pairs the output is a folder")
    names = [
        out / f"{r['id']}{ext}"
        for r in rows
        for ext in ((".npz", ".png") if args.preview else (".npz",))
    ]
    summary_path = out / "summary.csv"
    inputs = [Path(args.pairs)] + [r[k] for r in rows for k in ("map1", "map2")]
    kinds = [None] * len(names) + ["fuse-summary"]  # by suffix; the summary table
    with OutputSet([*names, summary_path], kinds=kinds, inputs=inputs, force=args.force) as outs:
        model = api.load_fusion(args.model, tracking_uri=args.tracking_uri)
        t0 = time.perf_counter()
        table = []
        pairs = _fusion_pairs(rows, args.cell)
        for r, res in zip(rows, api.fuse(model, pairs, batch_size=args.batch_size)):
            pose1, pose2 = r.pop("_poses")
            png = out / f"{res.id}.png" if args.preview else None
            _write_fused(outs, out / f"{res.id}.npz", res, pose1, pose2, png)
            table.append(_summary_row(r, res, out))
        seconds = time.perf_counter() - t0
        outs.write_text(summary_path, _csv_text(table))
        outs.commit()
    print(
        json.dumps(
            {
                "pairs": len(table),
                "output": str(out),
                "summary": str(summary_path),
                "model": model.description,
                "batch_size": args.batch_size,
                "fuse_s": round(seconds, 3),
            },
            indent=2,
        )
    )
    return 0


def _fusion_pairs(rows: list[dict[str, Any]], cell_option: float | None) -> Iterator[Any]:
    """The pairs of the list as :class:`traffictwin.api.FusePair`, each map read only when the
    batch that holds it runs; the poses used are kept in the row (``_poses``)."""
    from traffictwin import api

    for r in rows:
        m1, c1, p1 = api.load_masses(r["map1"])
        m2, c2, p2 = api.load_masses(r["map2"])
        pose1 = r["pose1"] if r["pose1"] is not None else p1
        pose2 = r["pose2"] if r["pose2"] is not None else p2
        if pose1 is None or pose2 is None:
            raise CliError(
                f"--pairs: pair {r['id']!r}: no pose (list columns x1..yaw2 or 'pose' in {r['map1']} / {r['map2']})"
            )
        if m1.shape != m2.shape:
            raise CliError(
                f"{r['map2']}: grid size {m2.shape[1:]} differs from {r['map1']}'s {m1.shape[1:]}"
            )
        cell = cell_option if cell_option is not None else r["cell"] or c1 or c2
        r["_poses"] = (pose1, pose2)
        yield api.FusePair(m1, m2, pose1, pose2, cell, r["id"])


def _summary_row(r: dict[str, Any], res: Any, out: Path) -> dict[str, Any]:
    """The row of ``summary.csv`` of one fused pair."""
    return {
        "id": res.id,
        "map1": str(r["map1"]),
        "map2": str(r["map2"]),
        "output": str(out / f"{res.id}.npz"),
        "cell_m": res.cell,
        "rel_x": float(res.rel_pose[0]),
        "rel_y": float(res.rel_pose[1]),
        "rel_yaw": float(res.rel_pose[2]),
        "mean_u": float(res.u.mean()),
        "occupied_cells": _occupied(res),
    }


def _csv_text(table: list[dict[str, Any]]) -> str:
    buf = io.StringIO()
    wr = csv.DictWriter(buf, fieldnames=list(table[0]), lineterminator="\n")
    wr.writeheader()
    wr.writerows({k: csv_value(v) for k, v in row.items()} for row in table)
    return buf.getvalue()
