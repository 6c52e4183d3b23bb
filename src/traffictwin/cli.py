"""``traffictwin`` — the user-facing command (inference on your own files, registry, runs).

A thin layer over the public Python API :mod:`traffictwin.api` (models, fusion, risk) and
:mod:`traffictwin.export`. Global options: ``--version``, ``--threads N`` (torch CPU threads).

Subcommands::

    traffictwin fuse MAP1.npz MAP2.npz --pose1 x,y,yaw --pose2 x,y,yaw [--model REF]
                     [--tracking-uri URI] [--cell M] -o OUT [--force]
    traffictwin fuse --pairs LIST.csv|FOLDER [--model REF] [--batch-size 8] [--no-preview] -o OUTDIR
    traffictwin twin MAP1.npz MAP2.npz [MAP3.npz ...] --pose x,y,yaw --pose ... [--method ...] -o OUT
    traffictwin risk LEFT.png RIGHT.png [--speed M_S] [--model REF] [--params FILE] [--resize] [-o OUT.json]
    traffictwin risk FOLDER [--speed M_S] [--model REF] [--batch-size 16] [-o OUT.csv]
    traffictwin export fusion|risk --model REF -o MODEL.pt
    traffictwin rollback --model NAME [--version V] [--log FILE]
    traffictwin status [--model NAME ...]
    traffictwin runs compare --experiment fusion [--metrics a b ...] [--tracking-uri URI] [--wide]

Models (``--model REF``)
------------------------
A registry reference ``name@alias`` (e.g. ``traffictwin-risk@champion``) or a bare alias
(``champion`` / ``challenger``: ``traffictwin-risk`` for risk, ``traffictwin-fusion`` for
fusion: one network serves every pose-noise level), or the path of a model folder (``model.ckpt`` + ``model_meta.json``), which needs no
registry at all. The registry is ``--tracking-uri``, else ``MLFLOW_TRACKING_URI``, else the
project's ``mlflow.db`` (inside the project only); a missing database is an error, never created.
An unreachable registry is one line within seconds (MLflow's HTTP retries are bounded:
``MLFLOW_HTTP_REQUEST_MAX_RETRIES=0``, ``MLFLOW_HTTP_REQUEST_TIMEOUT=5`` unless set).

Input formats
-------------
- Evidential grid map (``fuse``): a ``.npz`` with ``m_free`` and ``m_occ``, each a ``(H, W)``
  float array of masses in the map's own sensor frame (row 0 = front/+x, col 0 = left/+y, sensor
  at the centre), on the simplex, no NaN. Optional scalar ``cell`` (m per cell) and ``pose``
  (x, y, yaw of the sensor in the world; m, m, rad). The grid (rows, cols, cell) must be the
  model's training grid.
- Poses: ``x,y,yaw`` in a common world frame, metres and **radians** (for a negative first value
  write ``--pose1=-3,2,0.1``).
- ``fuse --pairs``: a CSV with columns ``map1,map2`` and optionally ``id``, ``x1,y1,yaw1,x2,y2,yaw2``
  (else the maps' own ``pose``) and ``cell``; relative paths are relative to the CSV's folder. Or
  a FOLDER of ``<id>_1.npz`` / ``<id>_2.npz`` maps that carry their ``pose``. Output folder:
  ``<id>.npz`` (+ ``<id>.png`` unless ``--no-preview``) per pair and ``summary.csv``.
- Stereo pairs (``risk``): rectified 8-bit images readable by OpenCV of equal size, the size of
  the model's training camera (``domain.camera`` of its metadata) unless ``--resize`` (both
  images resized to it before ORB and SGM: the disparity is then in the camera's pixel scale). A
  folder holds pairs named ``<id>_left.<ext>`` / ``<id>_right.<ext>``; they are streamed in
  batches (``--batch-size``) and the result is a CSV with one row per ``<id>``. SGM/ORB settings
  are those of the model's metadata (``domain.sgm`` / ``domain.orb``), else ``risk_data.sgm`` /
  ``risk_data.orb`` of ``--params FILE``, else the library defaults.
- ``--speed`` (m/s) is checked against the model's training speed range (``domain.speed_range``
  or ``domain.max_speed`` of its metadata, else ``risk_data.max_speed`` of ``--params``); a model
  without a speed input gets a warning (the speed then only scales ``gap_m``).

Outputs
-------
``risk`` clamps the risk to [0, 1]; THW and gap are ``null`` in JSON and empty in CSV when
nothing is ahead (never ``inf``). Every command: an output that is an input, an existing output
without ``--force``, or a directory named as output file is refused; missing parent folders are
created; all outputs are written to temp files and renamed at the end, so nothing is
half-written.

Output of ``fuse``: ``OUT.npz`` with ``m_free``, ``m_occ``, ``u`` (float32, map 1's frame) and
the poses used, plus ``OUT.png``: map 1, map 2 prealigned, fused (red = m_occ, green = m_free,
blue = u). Output of ``twin``: ``OUT.npz`` with ``m_free``, ``m_occ``, ``u`` (the twin, first
map's frame), ``used`` / ``accepted`` per map, ``rel_pose_used`` / ``rel_pose_given`` (N, 3) and
``cell``, plus ``OUT.png``. Output of ``export``: a TorchScript file (:mod:`traffictwin.export`).

Promotion is not a command here: it needs the project's data, model folders and gate settings
(params.yaml), so it is a workflow of the repository (``python -m pipelines.promote``).

Errors exit with status 1 and one line naming the file/argument and the problem.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import os
import sys
import time
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from traffictwin import __version__
from traffictwin.api import (  # noqa: F401 - re-exported: the CLI's helpers live in the API
    ALIASES,
    DIVISOR,
    HTTP_ENV,
    IMAGE_EXTS,
    ApiError,
    ApiWarning,
    StereoSettings,
    risk_verdict,
    stereo_settings,
)
from traffictwin.io.jsonio import json_clean
from traffictwin.io.outputs import OutputError, OutputSet
from traffictwin.risk.metric import CRITICAL_THW
from traffictwin.threads import passive_omp_wait, pin_threads

CliError = ApiError  # one user-facing error type for the CLI and the API


#: the API's argument names and the CLI options that set them: API errors start with the argument
API_OPTIONS = {
    "speed": "--speed",
    "params_path": "--params",
    "thw_threshold": "--thw-threshold",
    "batch_size": "--batch-size",
}


def _in_cli_terms(message: str) -> str:
    """An API error message with its leading argument name replaced by the CLI option."""
    head, sep, rest = message.partition(":")
    return f"{API_OPTIONS[head]}{sep}{rest}" if sep and head in API_OPTIONS else message


def _first_line(exc: BaseException, limit: int = 300) -> str:
    text = str(exc).strip().splitlines()
    return (text[0] if text else repr(exc))[:limit]


def csv_value(v: Any) -> Any:
    """A CSV cell: non-finite floats (THW when nothing is ahead, ...) are empty, never ``inf``."""
    return "" if isinstance(v, float) and not math.isfinite(v) else v


def load_masses(path: str | Path) -> tuple[np.ndarray, float | None]:
    """Masses ``(2, H, W)`` and optional ``cell`` of a grid ``.npz`` (:func:`traffictwin.api.load_masses`)."""
    from traffictwin.api import load_masses as _load

    m, cell, _ = _load(path)
    return m, cell


def parse_pose(text: str, name: str) -> np.ndarray:
    """``"x,y,yaw"`` (m, m, rad) -> float64 (3,); errors name the option."""
    parts = [p.strip() for p in str(text).split(",")]
    if len(parts) != 3:
        raise CliError(
            f"{name}: expected three comma-separated numbers x,y,yaw (m, m, rad), got {text!r}"
        )
    try:
        vals = np.array([float(p) for p in parts], dtype=np.float64)
    except ValueError:
        raise CliError(f"{name}: expected numbers x,y,yaw (m, m, rad), got {text!r}") from None
    if not np.all(np.isfinite(vals)):
        raise CliError(f"{name}: pose values must be finite, got {text!r}")
    return vals


def _positive_cell(cell: float | None) -> None:
    if cell is not None and not (cell > 0 and math.isfinite(cell)):
        raise CliError(f"--cell: must be a positive number of metres, got {cell}")


def _npz_png(output: str) -> tuple[Path, Path]:
    out = Path(output)
    base = out.with_suffix("") if out.suffix == ".npz" else out
    return base.with_name(base.name + ".npz"), base.with_name(base.name + ".png")


def _png_bytes(img: np.ndarray) -> bytes:
    import cv2

    ok, png = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 1])  # fast; PNG is lossless
    if not ok:
        raise CliError("could not encode the PNG preview")
    return png.tobytes()


def _npz_bytes(**arrays: Any) -> bytes:
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


# ============================================================================ fuse


def mass_panels(
    panels: list[tuple[np.ndarray, np.ndarray | None]], titles: list[str] | None = None
) -> np.ndarray:
    """BGR uint8 image of mass maps side by side, white separators, upscaled to ~384 px tall,
    the colour map's legend below: each panel ``(masses (2, H, W), u (H, W) or None = 1 - m_free -
    m_occ)``; the report's colour map (:mod:`traffictwin.report.colours`: green = free,
    red = occupied, grey = unknown, mixtures in between). With ``titles`` (one per panel, ASCII:
    OpenCV's Hershey font), a white strip above the panels carries each panel's title, centred
    over it (font shrunk, then the text shortened with ``..``, to fit the panel's width)."""
    import cv2

    from traffictwin.report.colours import legend_strip_bgr8, masses_to_bgr8

    if titles is not None and len(titles) != len(panels):
        raise ValueError(f"mass_panels: {len(titles)} titles for {len(panels)} panels")
    h = panels[0][0].shape[1]
    scale = max(1, int(round(384 / h)))
    sep_w = 4 * scale
    parts, widths = [], []
    for k, (mm, uu) in enumerate(panels):
        rgb = masses_to_bgr8(mm, uu)
        parts.append(np.repeat(np.repeat(rgb, scale, axis=0), scale, axis=1) if scale > 1 else rgb)
        widths.append(parts[-1].shape[1])
        if k < len(panels) - 1:
            parts.append(np.full((h * scale, sep_w, 3), 255, np.uint8))
    img = np.concatenate(parts, axis=1)
    rows = [img, legend_strip_bgr8(img.shape[1])]
    if titles is not None:
        font, height = cv2.FONT_HERSHEY_SIMPLEX, 24
        strip = np.full((height, img.shape[1], 3), 255, np.uint8)
        x0 = 0
        for title, w in zip(titles, widths):
            text, size = str(title), 0.5

            def fits(t: str, f: float, w: int = w) -> bool:
                return cv2.getTextSize(t, font, f, 1)[0][0] <= w - 4

            while size > 0.35 and not fits(text, size):
                size -= 0.05
            while len(text) > 3 and not fits(text, size):
                text = text[:-3].rstrip() + ".."
            (tw, th), _ = cv2.getTextSize(text, font, size, 1)
            org = (x0 + max(0, (w - tw) // 2), (height + th) // 2)
            cv2.putText(strip, text, org, font, size, (0, 0, 0), 1, cv2.LINE_AA)
            x0 += w + sep_w
        rows.insert(0, strip)
    return np.concatenate(rows, axis=0)


def preview_image(m1: np.ndarray, m2w: np.ndarray, m: np.ndarray, u: np.ndarray) -> np.ndarray:
    """BGR uint8 preview: map 1 | map 2 moved into map 1's frame by the given poses | the fused
    map (its ``u`` = the grey), each titled, the colour legend below (:func:`mass_panels`)."""
    return mass_panels(
        [(m1, None), (m2w, None), (m, u)],
        titles=["map 1", "map 2 in map 1's frame", "fused (grey = uncertainty u)"],
    )


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
        image = preview_image(res.m1, res.m2_prealigned, res.masses, res.u)
        outs.write_bytes(preview, _png_bytes(image))


def _occupied(res: Any) -> int:
    return int(((res.masses[1] + res.u / 2) > 0.5).sum())


def cmd_fuse(args: argparse.Namespace) -> int:
    from traffictwin import api

    _positive_cell(args.cell)
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
    if c1 is not None and c2 is not None and abs(c1 - c2) > 1e-9:
        raise CliError(f"{args.map2}: cell size {c2} m differs from {args.map1}'s {c1} m")
    own = c1 if c1 is not None else c2
    if args.cell is not None and own is not None and abs(args.cell - own) > 1e-9:
        raise CliError(f"--cell: {args.cell} m contradicts the maps' own cell size {own} m")
    npz_path, png_path = _npz_png(args.output)
    with OutputSet([npz_path, png_path], inputs=[args.map1, args.map2], force=args.force) as outs:
        model = api.load_fusion(args.model, tracking_uri=args.tracking_uri)
        cell = args.cell if args.cell is not None else c1 if c1 is not None else c2
        cell = api.check_fusion_domain(model, (h, w), cell, str(args.map1))
        t0 = time.perf_counter()
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
    }
    print(json.dumps(json_clean(summary), indent=2))
    return 0


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
    rows: list[dict[str, Any]] = []
    if src.is_dir():
        ones = {p.name[: -len("_1.npz")]: p for p in sorted(src.glob("*_1.npz"))}
        twos = {p.name[: -len("_2.npz")]: p for p in sorted(src.glob("*_2.npz"))}
        lonely = sorted(set(ones) ^ set(twos))
        if lonely:
            raise CliError(
                f"--pairs: {src}: map '{lonely[0]}_1.npz' or '{lonely[0]}_2.npz' has no partner"
            )
        if not ones:
            raise CliError(f"--pairs: {src}: no pairs found (expected <id>_1.npz / <id>_2.npz)")
        rows = [
            {"id": k, "map1": ones[k], "map2": twos[k], "pose1": None, "pose2": None, "cell": None}
            for k in sorted(ones)
        ]
    elif src.is_file():
        try:
            with open(src, newline="") as fh:
                table = list(csv.DictReader(fh))
        except (OSError, UnicodeDecodeError, csv.Error) as exc:
            raise CliError(f"--pairs: {src}: not a readable CSV ({exc})") from None
        if not table:
            raise CliError(
                f"--pairs: {src}: no rows (expected columns map1,map2[,id,x1,y1,yaw1,x2,y2,yaw2,cell])"
            )
        cols = set(table[0])
        if not {"map1", "map2"} <= cols:
            raise CliError(
                f"--pairs: {src}: columns map1 and map2 are required (has {sorted(cols)})"
            )
        has_pose = [c in cols for c in _POSE_COLS]
        if any(has_pose) and not all(has_pose):
            raise CliError(
                f"--pairs: {src}: pose columns must be all of {', '.join(_POSE_COLS)} or none"
            )
        header = list(table[0])
        for k, r in enumerate(table, start=2):
            if None in r or any(v is None for v in r.values()):
                n = len([v for v in r.values() if v is not None]) + len(r.get(None) or [])
                raise CliError(
                    f"--pairs: {src} line {k}: {n} field(s), but the header has {len(header)} "
                    f"({','.join(header)})"
                )
            empty = [c for c in ("map1", "map2") if not r[c].strip()]
            if empty:
                raise CliError(f"--pairs: {src} line {k}: column {empty[0]} is empty (a .npz file)")
            pose_cols = _POSE_COLS if all(has_pose) else ()
            bad = [c for c in pose_cols if not (r[c].strip() and _number(r[c]))]
            bad += [] if _number(r.get("cell")) else ["cell"]
            if bad:
                raise CliError(
                    f"--pairs: {src} line {k}: column {bad[0]} = {r[bad[0]]!r} is not a number"
                )
            pose = [float(r[c]) for c in _POSE_COLS] if all(has_pose) else None
            cell = float(r["cell"]) if r.get("cell") not in (None, "") else None
            if pose is not None and not np.all(np.isfinite(pose)):
                raise CliError(f"--pairs: {src} line {k}: pose values must be finite")
            _positive_cell(cell)
            rows.append(
                {
                    "id": (r.get("id") or f"{k - 1:05d}").strip(),
                    "map1": src.parent / r["map1"],
                    "map2": src.parent / r["map2"],
                    "pose1": None if pose is None else np.array(pose[:3]),
                    "pose2": None if pose is None else np.array(pose[3:]),
                    "cell": cell,
                }
            )
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


def _fuse_many(args: argparse.Namespace) -> int:
    from traffictwin import api

    if args.map1 is not None:
        raise CliError("--pairs: pass either MAP1 MAP2 or --pairs, not both")
    if args.pose1 is not None or args.pose2 is not None:
        raise CliError(
            "--pairs: poses come from the list (x1..yaw2) or the maps' 'pose', not --pose1/--pose2"
        )
    rows = read_pair_list(args.pairs)
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
    with OutputSet([*names, summary_path], inputs=inputs, force=args.force) as outs:
        model = api.load_fusion(args.model, tracking_uri=args.tracking_uri)
        t0 = time.perf_counter()

        def pairs() -> Iterator[Any]:
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
                cell = args.cell if args.cell is not None else r["cell"] or c1 or c2
                r["_poses"] = (pose1, pose2)
                yield api.FusePair(m1, m2, pose1, pose2, cell, r["id"])

        table = []
        for r, res in zip(rows, api.fuse(model, pairs(), batch_size=args.batch_size)):
            pose1, pose2 = r.pop("_poses")
            png = out / f"{res.id}.png" if args.preview else None
            _write_fused(outs, out / f"{res.id}.npz", res, pose1, pose2, png)
            table.append(
                {
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
            )
        seconds = time.perf_counter() - t0
        buf = io.StringIO()
        wr = csv.DictWriter(buf, fieldnames=list(table[0]), lineterminator="\n")
        wr.writeheader()
        wr.writerows({k: csv_value(v) for k, v in row.items()} for row in table)
        outs.write_text(summary_path, buf.getvalue())
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


# ============================================================================ twin


def load_twin_models(
    method: str, registration_model: str | None, fusion_model: str | None
) -> dict[str, Any]:
    """The models a twin method needs, from model folders/checkpoints (``--registration-model``:
    a learned registration, ``models/registration/<cfg>``; ``--fusion-model``: a fusion network)."""
    from traffictwin.fusion.model_io import FusionModelError, load_fusion_model
    from traffictwin.fusion.registration_training import load_registration_model
    from traffictwin.twin.fuse import TWIN_METHODS

    needs = TWIN_METHODS[method].needs
    models: dict[str, Any] = {}
    for need, path, opt, load in (
        ("registration", registration_model, "--registration-model", load_registration_model),
        ("fusion", fusion_model, "--fusion-model", load_fusion_model),
    ):
        if need not in needs:
            if path is not None:
                raise CliError(
                    f"{opt}: method '{method}' does not use a {need} model (it would be ignored)"
                )
            continue
        if path is None:
            raise CliError(f"{opt}: method '{method}' needs a {need} model folder or .ckpt")
        if not Path(path).exists():
            raise CliError(f"{opt}: '{path}' does not exist")
        try:
            models[need] = load(Path(path))
        except FusionModelError as exc:
            raise CliError(str(exc)) from None
    return models


def twin_preview(twin: np.ndarray, contributions: list[np.ndarray]) -> np.ndarray:
    """BGR uint8 preview: the twin | each vehicle's map where the twin put it, titled by the
    maps' order on the command line (map 1 the reference), the colour legend below
    (:func:`mass_panels`); a left-out map is passed as all zeros (grey = unknown) and titled
    so."""
    titles = ["twin (the maps fused)"]
    for k, c in enumerate(contributions):
        if k == 0:
            titles.append("map 1 (reference)")
        elif not np.any(c):
            titles.append(f"map {k + 1}: left out")
        else:
            titles.append(f"map {k + 1} where the twin put it")
    return mass_panels([(twin, None), *((c, None) for c in contributions)], titles=titles)


def cmd_twin(args: argparse.Namespace) -> int:
    from traffictwin.evidential.warp import warp_masses
    from traffictwin.geometry import relative_pose
    from traffictwin.grid import GridSpec
    from traffictwin.twin.fuse import TwinInputError, build_twin

    if len(args.maps) < 2:
        raise CliError(f"maps: a twin needs at least two maps, got {len(args.maps)}")
    poses = args.pose or []
    if len(poses) != len(args.maps):
        raise CliError(
            f"--pose: give one x,y,yaw per map in the same order ({len(args.maps)} maps, {len(poses)} poses)"
        )
    world = [parse_pose(p, f"--pose #{k + 1} ({args.maps[k]})") for k, p in enumerate(poses)]
    loaded = [load_masses(m) for m in args.maps]
    ref_m, ref_c = loaded[0]
    for path, (m, c) in zip(args.maps[1:], loaded[1:]):
        if m.shape != ref_m.shape:
            raise CliError(
                f"{path}: grid size {m.shape[1:]} differs from {args.maps[0]}'s {ref_m.shape[1:]} (rows, cols)"
            )
        if c is not None and ref_c is not None and abs(c - ref_c) > 1e-9:
            raise CliError(f"{path}: cell size {c} m differs from {args.maps[0]}'s {ref_c} m")
    cells = {c for _, c in loaded if c is not None}
    if args.cell is not None and not (args.cell > 0 and math.isfinite(args.cell)):
        raise CliError(f"--cell: must be a positive number of metres, got {args.cell}")
    if args.cell is not None and cells and abs(args.cell - next(iter(cells))) > 1e-9:
        raise CliError(
            f"--cell: {args.cell} m contradicts the maps' own cell size {next(iter(cells))} m"
        )
    cell = args.cell if args.cell is not None else (next(iter(cells)) if cells else None)
    if cell is None:
        raise CliError(
            "grid cell size unknown: pass --cell (m per cell) or store 'cell' in the .npz files"
        )
    models = load_twin_models(args.method, args.registration_model, args.fusion_model)
    from traffictwin import api

    for need, net in models.items():  # the networks run only on the grid they were trained on
        meta = dict(getattr(net, "meta", {}) or {})
        opt = "--fusion-model" if need == "fusion" else "--registration-model"
        desc = f"{opt} {args.fusion_model if need == 'fusion' else args.registration_model}"
        api.check_fusion_domain(
            api.FusionModel(net, meta, dict(meta.get("grid") or {}), desc),
            tuple(ref_m.shape[1:]),
            cell,
            str(args.maps[0]),
        )
    npz_path, png_path = _npz_png(args.output)
    outs = OutputSet([npz_path, png_path], inputs=args.maps, force=args.force)
    grid = GridSpec(rows=ref_m.shape[1], cols=ref_m.shape[2], cell=cell)
    maps = np.stack([m for m, _ in loaded])
    rel = np.stack([np.zeros(3)] + [relative_pose(world[0], w) for w in world[1:]])
    try:
        step = build_twin(maps, rel, grid, args.method, strategy=args.strategy, models=models)
    except TwinInputError as exc:
        raise CliError(str(exc)) from None
    contributions = [maps[0]] + [
        warp_masses(maps[k], step.poses[k], grid) if step.used[k] else np.zeros_like(maps[k])
        for k in range(1, len(maps))
    ]
    png = _png_bytes(twin_preview(step.masses, contributions))
    u = 1.0 - step.masses[0] - step.masses[1]
    data = _npz_bytes(
        m_free=step.masses[0],
        m_occ=step.masses[1],
        u=u.astype(np.float32),
        used=step.used,
        accepted=step.accepted,
        rel_pose_used=step.poses,
        rel_pose_given=rel,
        cell=np.float64(cell),
    )
    with outs:
        outs.write_bytes(npz_path, data)
        outs.write_bytes(png_path, png)
        outs.commit()
    summary = {
        "output": str(npz_path),
        "preview": str(png_path),
        "method": args.method,
        "strategy": args.strategy,
        "vehicles": len(maps),
        "used": [bool(v) for v in step.used],
        "left_out": [args.maps[k] for k in range(len(maps)) if not step.used[k]],
        "rel_pose_used": [[float(v) for v in p] for p in step.poses],
        "twin_ms": round(1000.0 * step.seconds, 2),
        "occupied_cells": int((step.masses[1] >= 0.5).sum()),
    }
    print(json.dumps(json_clean(summary), indent=2))
    return 0


# ============================================================================ risk


def _risk_frames(args: argparse.Namespace) -> tuple[list[Any], bool]:
    from traffictwin import api

    src = Path(args.left)
    if src.is_dir():
        if args.right is not None:
            raise CliError(
                f"{src} is a folder: pass no RIGHT image (pairs are found by *_left/*_right names)"
            )
        return api.frames_in_folder(src), True
    if args.right is None:
        raise CliError(
            f"{src}: pass LEFT and RIGHT images, or a folder of <id>_left/<id>_right pairs"
        )
    for p in (src, Path(args.right)):
        if not p.is_file():
            raise CliError(f"{p}: image not found")
    return [api.Frame(src.stem, src, Path(args.right))], False


def cmd_risk(args: argparse.Namespace) -> int:
    from traffictwin import api

    if args.speed is not None and not (math.isfinite(args.speed) and args.speed >= 0):
        raise CliError(f"--speed: must be a finite speed >= 0 m/s, got {args.speed}")
    api.check_thw_threshold(args.thw_threshold, "--thw-threshold")
    if args.batch_size < 1:
        raise CliError(f"--batch-size: must be >= 1, got {args.batch_size}")
    frames, is_folder = _risk_frames(args)
    out = Path(args.output) if args.output else None
    inputs = [p for f in frames for p in (f.left, f.right)] + (
        [Path(args.params)] if args.params else []
    )
    outs = OutputSet([out] if out else [], inputs=inputs, force=args.force)
    for f in frames:  # every image's header before the model (and torch) loads: a huge or
        for p in (f.left, f.right):  # broken image is refused in a fraction of a second
            api.check_image_file(p)
    rmodel = api.load_risk(args.model, tracking_uri=args.tracking_uri)
    for note in api.check_speed(rmodel, args.speed, args.params):
        warnings.warn(note, ApiWarning, stacklevel=1)
    st = api.stereo_settings(rmodel.domain, args.params, rmodel.description)
    paths = {f.id: (str(f.left), str(f.right)) for f in frames}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ApiWarning)  # check_speed's notes: printed once above
        rows = api.assess_risk(
            rmodel,
            frames,
            speed=args.speed,
            settings=st,
            resize=args.resize,
            batch_size=args.batch_size,
            thw_threshold=args.thw_threshold,
        )
        with outs:
            if not is_folder:
                row = next(rows)
                lp, rp = paths[row["id"]]
                res = json_clean(
                    {
                        "id": row["id"],
                        "left": lp,
                        "right": rp,
                        **row,
                        "model": rmodel.description,
                        "predictor": rmodel.predictor,
                        "stereo_settings": st.source,
                    }
                )
                if out:
                    outs.write_text(out, json.dumps(res, indent=2, sort_keys=True) + "\n")
                    outs.commit()
                print(json.dumps(res, indent=2))
                return 0
            fh = outs.open(out, "w", newline="") if out else sys.stdout
            try:
                wr = None
                n = 0
                for row in rows:
                    lp, rp = paths[row["id"]]
                    row = {"id": row["id"], "left": lp, "right": rp, **row}
                    if wr is None:
                        wr = csv.DictWriter(fh, fieldnames=list(row), lineterminator="\n")
                        wr.writeheader()
                    wr.writerow({k: csv_value(v) for k, v in row.items()})
                    n += 1
            finally:
                if out:
                    fh.close()
            if out:
                outs.commit()
                print(
                    f"{n} pair(s) -> {out} (model {rmodel.description}, predictor {rmodel.predictor}; "
                    f"stereo settings: {st.source})"
                )
    return 0


# ============================================================================ export


def cmd_export(args: argparse.Namespace) -> int:
    from traffictwin import api

    out = Path(args.output)
    with OutputSet([out], force=args.force) as outs:
        from traffictwin import export

        if args.problem == "fusion":
            fm = api.load_fusion(args.model, tracking_uri=args.tracking_uri)
            if not {"rows", "cols"} <= set(fm.grid):
                raise CliError(
                    f"--model: {fm.description} records no training grid (rows, cols) to trace on"
                )
            module, meta = export.export_fusion(fm.net, fm.grid)
            desc = fm.description
        else:
            rm = api.load_risk(args.model, tracking_uri=args.tracking_uri)
            if not hasattr(rm.model, "net") or hasattr(rm.model, "predict_features"):
                raise CliError(
                    f"--model: {rm.description} is a {rm.predictor} risk predictor, not the DAVE-2 "
                    "network; only the network exports to TorchScript (serve the predictor with "
                    "`traffictwin risk` or the Python API)"
                )
            module, meta = export.export_risk(rm.model)
            desc = rm.description
        meta["source"] = desc
        meta["traffictwin_version"] = __version__
        export.save(module, outs.temp_path(out), meta)
        outs.commit()
    print(
        json.dumps(
            {
                "output": str(out),
                "model": desc,
                "input": meta["input"],
                "output_layout": meta["output"],
            },
            indent=2,
        )
    )
    return 0


# ============================================================================ registry / runs


def _registry_client(args: argparse.Namespace):
    from traffictwin import api

    return api.connect(getattr(args, "tracking_uri", None))


def cmd_rollback(args: argparse.Namespace) -> int:
    from traffictwin.mlops import registry as reg

    cl = _registry_client(args)
    log_path = Path(args.log) if args.log else reg.promotion_log(cl, args.model)
    try:
        # never between a gate's decision and its apply
        with reg.gate_lock(reg.default_lock_path(cl.tracking_uri)):
            rec = reg.rollback(cl, args.model, args.version, log_path=log_path)
    except reg.RegistryError as exc:
        raise CliError(str(exc)) from None
    print(f"{rec['name']}: champion v{rec['from_version']} -> v{rec['to_version']}")
    if log_path is None:
        print("(no promotion log recorded for this model: pass --log FILE to log the rollback)")
    return 0


def cmd_status(args: argparse.Namespace) -> int:
    from traffictwin.mlops import registry as reg

    cl = _registry_client(args)
    names = args.model or sorted(
        m.name for m in cl.search_registered_models() if m.name.startswith("traffictwin-")
    )
    rows = reg.status(cl, names)
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    if not rows:
        print(
            "no traffictwin models registered yet "
            "(run the promotion gate after `dvc repro`: `python -m pipelines.promote`)"
        )
    for r in rows:
        ch, cd = r["champion"], r["challenger"]
        print(
            f"{r['name']:28s} champion {'v' + ch['version'] if ch else '-':>5s}   challenger "
            f"{'v' + cd['version'] if cd else '-':>5s} ({(cd or {}).get('decision') or '-'})   history {r['history']}"
        )
    return 0


def cmd_runs_compare(args: argparse.Namespace) -> int:
    from traffictwin import api
    from traffictwin.mlops.runs import RunsError, compare_runs, format_runs

    outs = OutputSet([args.csv] if args.csv else [], force=args.force, option="--csv")
    uri = api.resolve_tracking_uri(args.tracking_uri)
    try:
        df = compare_runs(args.experiment, metrics=args.metrics, uri=uri)
    except RunsError as exc:
        raise CliError(str(exc)) from None
    if args.csv:
        with outs:
            outs.write_text(args.csv, df.to_csv(index=False))
            outs.commit()
    print(format_runs(df, wide=args.wide))
    return 0


# ============================================================================ parser


def _model_options(p: argparse.ArgumentParser, what: str, registry: str) -> None:
    p.add_argument(
        "--model",
        default="champion",
        help=f"{what}: registry reference name@alias, or champion | challenger of {registry}, "
        "or a model folder (no registry needed); default champion",
    )
    _uri_option(p)


def _uri_option(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--tracking-uri",
        default=None,
        help="MLflow tracking/registry URI (default: MLFLOW_TRACKING_URI, else the project's "
        "mlflow.db; a missing database is never created)",
    )


def _output_options(p: argparse.ArgumentParser, help_text: str, required: bool = True) -> None:
    p.add_argument("-o", "--output", required=required, default=None, help=help_text)
    p.add_argument(
        "--force",
        action="store_true",
        help="overwrite a previous output of this kind (never an input, a model folder, the "
        "MLflow store or a DVC file)",
    )


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="traffictwin",
        description="traffictwin: cooperative OGM fusion and stereo risk — inference, registry, runs.",
    )
    ap.add_argument("--version", action="version", version=f"traffictwin {__version__}")
    ap.add_argument(
        "--threads",
        type=int,
        default=None,
        help="torch CPU threads (default: torch's choice; 1 is fastest for single items on a busy machine)",
    )
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")

    f = sub.add_parser(
        "fuse",
        help="fuse two evidential grid maps (or many pairs) with the fusion network",
        description="Prealign MAP2 into MAP1's frame by the poses and fuse them with the network; "
        "--pairs fuses many pairs in one call with batched inference.",
    )
    f.add_argument(
        "map1", nargs="?", default=None, help=".npz with m_free, m_occ (H, W) masses, ego map"
    )
    f.add_argument(
        "map2", nargs="?", default=None, help=".npz of the other vehicle's map, same size"
    )
    f.add_argument(
        "--pose1", default=None, help="x,y,yaw of map 1's sensor in the world (m, m, rad)"
    )
    f.add_argument(
        "--pose2", default=None, help="x,y,yaw of map 2's sensor in the world (m, m, rad)"
    )
    f.add_argument(
        "--pairs",
        default=None,
        help="a CSV list (map1,map2[,id,x1,y1,yaw1,x2,y2,yaw2,cell]) or a folder of <id>_1.npz/<id>_2.npz",
    )
    _model_options(f, "fusion model", "traffictwin-fusion")
    f.add_argument(
        "--cell",
        type=float,
        default=None,
        help="m per cell (default: the .npz 'cell', else the model's)",
    )
    f.add_argument(
        "--batch-size", type=int, default=8, help="pairs per forward pass with --pairs (default 8)"
    )
    f.add_argument(
        "--no-preview", dest="preview", action="store_false", help="with --pairs: no PNG per pair"
    )
    _output_options(
        f, "output base name: writes OUT.npz and OUT.png (with --pairs: an output folder)"
    )
    f.set_defaults(func=cmd_fuse)

    tw = sub.add_parser(
        "twin",
        help="fuse N vehicles' evidential grid maps into one twin in the first map's frame",
        description="Register every map onto the first (the reference vehicle's) from the given poses and "
        "combine them (traffictwin.twin.fuse); a map whose registration is rejected is left out and reported.",
    )
    tw.add_argument(
        "maps", nargs="+", help=".npz maps (m_free, m_occ; same format as `fuse`), reference first"
    )
    tw.add_argument(
        "--pose",
        action="append",
        help="x,y,yaw of a map's sensor in a common world frame (m, m, rad); once per map, in order",
    )
    tw.add_argument(
        "--method",
        default="registered",
        choices=("naive", "registered", "learned", "dnn", "registered+network", "learned+network"),
        help="pose source + combination (default registered: classical registration + Dempster, no model needed)",
    )
    tw.add_argument("--strategy", default="reference", choices=("reference", "sequential"))
    tw.add_argument(
        "--registration-model",
        default=None,
        help="learned registration folder/.ckpt (methods learned*)",
    )
    tw.add_argument(
        "--fusion-model", default=None, help="fusion network folder/.ckpt (methods dnn, *+network)"
    )
    tw.add_argument(
        "--cell", type=float, default=None, help="m per cell (default: the .npz 'cell')"
    )
    _output_options(tw, "output base name: writes OUT.npz and OUT.png")
    tw.set_defaults(func=cmd_twin)

    r = sub.add_parser(
        "risk",
        help="stereo risk: ORB check, SGM disparity, predicted risk and THW verdict",
        description="LEFT RIGHT images, or a FOLDER of <id>_left.png/<id>_right.png pairs (-> CSV, streamed in batches).",
    )
    r.add_argument("left", help="left image, or a folder of pairs")
    r.add_argument("right", nargs="?", default=None, help="right image (omit for a folder)")
    r.add_argument(
        "--speed",
        type=float,
        default=None,
        help="subject speed (m/s): gap = THW * speed; required by speed models, checked against the training range",
    )
    _model_options(r, "risk model", "traffictwin-risk")
    r.add_argument(
        "--thw-threshold",
        type=float,
        default=CRITICAL_THW,
        help=f"critical if THW below this (s), default {CRITICAL_THW}",
    )
    r.add_argument(
        "--params",
        default=None,
        help="params file with risk_data.sgm/orb/max_speed, used when the model's metadata lacks them",
    )
    r.add_argument(
        "--resize",
        action="store_true",
        help="resize images to the model's training camera size before ORB/SGM (else a size mismatch is an error)",
    )
    r.add_argument(
        "--batch-size", type=int, default=16, help="frames per batch for a folder (default 16)"
    )
    _output_options(
        r, "write the JSON (pair) or CSV (folder) here (default: stdout)", required=False
    )
    r.set_defaults(func=cmd_risk)

    e = sub.add_parser(
        "export",
        help="export a fusion or risk network as TorchScript",
        description="Trace the network on an input of its training shape and save it with torch.jit "
        "(loads with torch.jit.load alone; see traffictwin.export for the input/output layout).",
    )
    e.add_argument("problem", choices=("fusion", "risk"))
    _model_options(e, "model to export", "traffictwin-fusion / traffictwin-risk")
    _output_options(e, "the TorchScript file to write (e.g. fusion.pt)")
    e.set_defaults(func=cmd_export)

    b = sub.add_parser(
        "rollback", help="move the champion alias back (previous champion or --version)"
    )
    b.add_argument("--model", required=True, help="registered model name, e.g. traffictwin-fusion")
    b.add_argument(
        "--version", default=None, help="version to make champion (default: the previous champion)"
    )
    b.add_argument(
        "--log",
        default=None,
        help="promotion log to append to (default: the one the gate recorded on the model)",
    )
    _uri_option(b)
    b.set_defaults(func=cmd_rollback)

    s = sub.add_parser("status", help="champion / challenger of the registered models")
    s.add_argument(
        "--model",
        nargs="+",
        default=None,
        help="registered model names (default: all traffictwin-*)",
    )
    s.add_argument("--json", action="store_true")
    _uri_option(s)
    s.set_defaults(func=cmd_status)

    ru = sub.add_parser("runs", help="MLflow runs")
    rsub = ru.add_subparsers(dest="runs_command", required=True, metavar="SUBCOMMAND")
    c = rsub.add_parser("compare", help="compare the runs of an experiment as a table")
    c.add_argument("--experiment", required=True, help="MLflow experiment (fusion | risk | ...)")
    c.add_argument("--metrics", nargs="+", default=None, help="metric names (default: all)")
    c.add_argument(
        "--tracking-uri",
        "--uri",
        dest="tracking_uri",
        default=None,
        help="tracking URI (default: MLFLOW_TRACKING_URI or the project's mlflow.db)",
    )
    c.add_argument("--wide", action="store_true", help="full run ids and every tag column")
    c.add_argument("--csv", default=None, help="also write the table as CSV")
    c.add_argument(
        "--force",
        action="store_true",
        help="overwrite a previous --csv table (never the MLflow store or a DVC file)",
    )
    c.set_defaults(func=cmd_runs_compare)
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    for k, v in HTTP_ENV.items():  # a dead registry: one line in seconds, not minutes of retries
        os.environ.setdefault(k, v)
    # OpenMP threads that sleep instead of spinning while they wait (benchmarks/startup.py); set
    # before any torch import; an explicit setting wins
    passive_omp_wait()
    if args.threads is not None:
        if args.threads < 1:
            parser.error(f"--threads must be >= 1, got {args.threads}")
        pin_threads(args.threads)
    prog = f"traffictwin {args.command}"
    show = warnings.showwarning

    def one_line(message, category, filename, lineno, file=None, line=None):  # noqa: ANN001
        if issubclass(category, ApiWarning):
            print(f"{prog}: warning: {message}", file=sys.stderr)
        else:
            show(message, category, filename, lineno, file, line)

    warnings.showwarning = one_line
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always", ApiWarning)
            rc = args.func(args)
    except (ApiError, OutputError) as exc:
        print(f"{prog}: error: {_in_cli_terms(str(exc))}", file=sys.stderr)
        return 1
    except OSError as exc:  # read-only folder, full disk, ...: the file and the reason, one line
        where = exc.filename or "an output or input file"
        print(f"{prog}: error: {where}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    except (ValueError, TypeError) as exc:  # bad input the checks above did not name
        if os.environ.get("TRAFFICTWIN_DEBUG"):
            raise
        print(
            f"{prog}: error: {type(exc).__name__}: {_first_line(exc)} "
            "(set TRAFFICTWIN_DEBUG=1 for the traceback)",
            file=sys.stderr,
        )
        return 1
    except KeyboardInterrupt:
        return 130
    finally:
        warnings.showwarning = show
    return int(rc or 0)


if __name__ == "__main__":
    sys.exit(main())
