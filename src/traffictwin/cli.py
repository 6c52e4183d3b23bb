"""``traffictwin`` — the user-facing command (inference on your own files, registry, runs).

Subcommands (global option ``--threads N`` sets torch's CPU threads)::

    traffictwin fuse MAP1.npz MAP2.npz --pose1 x,y,yaw --pose2 x,y,yaw [--model champion|challenger|PATH]
                     [--config CFG] [--cell M] -o OUT
    traffictwin twin MAP1.npz MAP2.npz [MAP3.npz ...] --pose x,y,yaw --pose ... [--method registered|learned|...]
                     [--registration-model PATH] [--fusion-model PATH] [--strategy reference|sequential] -o OUT
    traffictwin risk LEFT.png RIGHT.png [--speed M_S] [--model champion|challenger|PATH] [--params FILE]
                     [-o OUT.json]
    traffictwin risk FOLDER [--speed M_S] [--model ...] [-o OUT.csv]
    traffictwin rollback --model NAME [--version V] [--log FILE]
    traffictwin status [--model NAME ...]
    traffictwin runs compare --experiment fusion [--metrics a b ...] [--uri URI] [--wide]

Input formats
-------------
- Evidential grid map (``fuse``): a ``.npz`` with ``m_free`` and ``m_occ``, each a ``(H, W)``
  float array (float32 preferred) of masses in the map's own sensor frame (row 0 = front/+x,
  col 0 = left/+y, sensor at the centre), every cell with ``m_free, m_occ >= 0`` and
  ``m_free + m_occ <= 1`` (``u = 1 - m_free - m_occ``), no NaN. Optional scalar ``cell``
  (m per cell). H and W must be divisible by 16 (the network's output stride).
- Poses: ``x,y,yaw`` in a common world frame, metres and **radians** (for a negative first
  value write ``--pose1=-3,2,0.1``).
- Stereo pairs (``risk``): rectified 8-bit images readable by OpenCV (PNG, JPEG…) of equal size.
  A folder holds pairs named ``<id>_left.<ext>`` / ``<id>_right.<ext>``; the result is a CSV with
  one row per ``<id>``. JSON output writes ``thw_s``/``gap_m`` as ``null`` when no vehicle is
  ahead (THW infinite); the CSV writes ``inf``. SGM/ORB settings are those the model's data were
  made with: ``domain.sgm`` / ``domain.orb`` of the model's metadata (``model_meta.json`` of a
  model folder; the logged model's metadata of a registered one), else ``risk_data.sgm`` /
  ``risk_data.orb`` of a params file passed as ``--params FILE``, else the library defaults.
- Registered fusion models are ``traffictwin-fusion-<CFG>``; ``--config`` names the pose-noise
  configuration (any name; without it, the only registered fusion model).

Promotion is not a command here: it needs the project's data, model folders and gate settings
(params.yaml), so it is a workflow of the repository (``python -m pipelines.promote``, which
calls :func:`traffictwin.mlops.promotion.promote`). This command only needs registry names:
``status`` and ``rollback`` (which logs to the promotion log recorded on the model, or ``--log``).

Output of ``twin``: ``OUT.npz`` with ``m_free``, ``m_occ``, ``u`` (the twin, first map's frame),
``used`` / ``accepted`` per map, ``rel_pose_used`` / ``rel_pose_given`` (N, 3) and ``cell``, plus
``OUT.png`` (the twin, then each map where the twin put it; a left-out map is all blue: unknown).

Output of ``fuse``: ``OUT.npz`` with ``m_free``, ``m_occ``, ``u`` (float32, map 1's frame) and
the poses used, plus ``OUT.png``: map 1, map 2 prealigned, fused (red = m_occ, green = m_free,
blue = u).

Errors (bad shapes, masses outside the simplex or NaN, unreadable images, mismatched sizes,
missing model alias, …) exit with status 1 and a message naming the file/argument and the
problem; nothing is written unless every input is valid (outputs are written atomically).
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from traffictwin.risk.metric import CRITICAL_THW, risk_to_thw

SIMPLEX_TOL = 1e-4
DIVISOR = 16
ALIASES = ("champion", "challenger")
IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm")


def json_safe(obj: Any) -> Any:
    """``obj`` with non-finite floats replaced by ``None`` (strict JSON; e.g. THW = inf -> null)."""
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


class CliError(Exception):
    """A user-facing error: printed as ``traffictwin <cmd>: error: <message>``, exit status 1."""


# ============================================================================ input validation


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


def load_masses(path: str | Path) -> tuple[np.ndarray, float | None]:
    """Read and validate an evidential grid ``.npz``: returns masses ``(2, H, W)`` float32 and the
    optional ``cell`` (m). Raises :class:`CliError` naming the file and the problem."""
    path = Path(path)
    if not path.is_file():
        raise CliError(f"{path}: file not found")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as exc:  # noqa: BLE001 - zip/format errors of all kinds
        raise CliError(f"{path}: not a readable .npz file ({type(exc).__name__}: {exc})") from None
    missing = [k for k in ("m_free", "m_occ") if k not in data]
    if missing:
        raise CliError(
            f"{path}: array(s) {missing} missing (has {sorted(data)}); expected m_free and m_occ, (H, W) float"
        )
    mf, mo = data["m_free"], data["m_occ"]
    for k, a in (("m_free", mf), ("m_occ", mo)):
        if a.ndim != 2:
            raise CliError(f"{path}: '{k}' must be a 2-D (H, W) grid, got shape {a.shape}")
        if not np.issubdtype(a.dtype, np.floating):
            raise CliError(f"{path}: '{k}' must be a float array of masses, got dtype {a.dtype}")
    if mf.shape != mo.shape:
        raise CliError(f"{path}: 'm_free' {mf.shape} and 'm_occ' {mo.shape} differ in shape")
    from traffictwin.evidential.masses import check_masses, clean_masses

    m = np.stack([mf, mo]).astype(np.float64)
    try:
        m = check_masses(m, f"{path}: masses (m_free, m_occ)", tol=SIMPLEX_TOL)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    m = clean_masses(m).astype(np.float32)
    cell = None
    if "cell" in data:
        c = np.asarray(data["cell"])
        if (
            c.size != 1
            or not np.issubdtype(c.dtype, np.number)
            or not (float(c) > 0 and math.isfinite(float(c)))
        ):
            raise CliError(f"{path}: 'cell' must be one positive number (m per cell), got {c!r}")
        cell = float(c)
    return m, cell


def read_image(path: str | Path) -> np.ndarray:
    """An 8-bit BGR image (grayscale is expanded to 3 channels); errors name the file."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise CliError(f"{path}: image not found")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise CliError(f"{path}: not a readable image (OpenCV could not decode it)")
    if img.dtype != np.uint8:
        raise CliError(f"{path}: expected an 8-bit image, got {img.dtype}")
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    elif img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    elif img.shape[2] != 3:
        raise CliError(
            f"{path}: expected a grayscale, BGR or BGRA image, got {img.shape[2]} channels"
        )
    return np.ascontiguousarray(img)


def find_pairs(folder: Path) -> list[tuple[str, Path, Path]]:
    """``(id, left, right)`` for every ``<id>_left.<ext>`` / ``<id>_right.<ext>`` in ``folder`` (sorted).

    Errors on a folder without pairs and on a left or right image without its partner.
    """
    lefts, rights = {}, {}
    for p in sorted(folder.iterdir()):
        if not p.is_file() or p.suffix.lower() not in IMAGE_EXTS:
            continue
        stem = p.stem
        if stem.endswith("_left"):
            lefts[stem[: -len("_left")]] = p
        elif stem.endswith("_right"):
            rights[stem[: -len("_right")]] = p
    lonely = sorted(set(lefts) ^ set(rights))
    if lonely:
        k = lonely[0]
        have = lefts.get(k) or rights.get(k)
        want = "_right" if k in lefts else "_left"
        raise CliError(
            f"{have}: no partner image '{k}{want}.*' in {folder} ({len(lonely)} unpaired image(s))"
        )
    if not lefts:
        raise CliError(f"{folder}: no stereo pairs found (expected <id>_left.png / <id>_right.png)")
    return [(k, lefts[k], rights[k]) for k in sorted(lefts)]


# ============================================================================ models


def _registry_client():
    from traffictwin.mlops import registry as reg

    return reg.client()


def _registered_params(cl, name: str, alias: str) -> tuple[str, dict[str, str]]:
    """URI of ``name@alias`` (error if missing) and its training run's params."""
    from traffictwin.mlops import registry as reg

    try:
        mv = reg.require_alias(cl, name, alias)
    except reg.RegistryError as exc:
        raise CliError(str(exc)) from None
    try:
        params = dict(cl.get_run(mv.run_id).data.params) if mv.run_id else {}
    except Exception:  # noqa: BLE001 - params only refine checks
        params = {}
    return reg.version_uri(name, mv.version), params


def fusion_model_name(cl, config: str | None) -> str:
    """``traffictwin-fusion-<config>``; without ``config`` the only registered fusion model."""
    from traffictwin.mlops import registry as reg

    if config:
        return reg.fusion_name(config)
    names = reg.registered_names(cl, reg.fusion_name(""))
    if len(names) == 1:
        return names[0]
    raise CliError(
        "--config: name the pose-noise configuration of the registered fusion model "
        + (f"(registered: {', '.join(names)})" if names else "(no fusion model is registered yet)")
    )


def load_fusion(model: str, config: str | None) -> tuple[Any, dict[str, Any], str]:
    """The fusion network for ``--model`` (an alias of ``traffictwin-fusion-<config>`` or a path),
    its training grid (dict, may be empty) and a description."""
    from traffictwin.fusion.model_io import FusionModelError, load_fusion_model
    from traffictwin.mlops import registry as reg

    if model in ALIASES:
        cl = _registry_client()
        name = fusion_model_name(cl, config)
        uri, params = _registered_params(cl, name, model)
        try:
            net = reg.load_registered(uri, load_fusion_model, cl=cl)
        except Exception as exc:  # noqa: BLE001
            raise CliError(
                f"{uri}: cannot load the registered model ({type(exc).__name__}: {exc})"
            ) from None
        grid = dict(getattr(net, "meta", {}).get("grid", {}) or {}) or {
            k: float(params[f"grid.{k}"]) for k in ("rows", "cols", "cell") if f"grid.{k}" in params
        }
        return net, grid, f"{name}@{model} ({uri})"

    p = Path(model)
    if not p.exists():
        raise CliError(
            f"--model: '{model}' is neither an alias ({', '.join(ALIASES)}) nor an existing path"
        )
    try:
        net = load_fusion_model(p)
    except FusionModelError as exc:
        raise CliError(str(exc)) from None
    return net, dict(getattr(net, "meta", {}).get("grid", {}) or {}), str(p)


def load_risk(model: str):
    """A :class:`~traffictwin.risk.model_io.RiskModel` for ``--model`` (alias of ``traffictwin-risk``
    or a path) and a description; ``RiskModel.meta`` holds the model's metadata (``domain``…)."""
    from traffictwin.mlops import registry as reg
    from traffictwin.risk.model_io import RiskModelError, load_risk_model

    if model in ALIASES:
        cl = _registry_client()
        uri, _ = _registered_params(cl, reg.RISK_NAME, model)
        try:
            rmodel = reg.load_registered(uri, load_risk_model, cl=cl)
        except Exception as exc:  # noqa: BLE001
            raise CliError(
                f"{uri}: cannot load the registered risk model ({type(exc).__name__}: {exc})"
            ) from None
        return rmodel, f"{reg.RISK_NAME}@{model} ({uri})"
    p = Path(model)
    if not p.exists():
        raise CliError(
            f"--model: '{model}' is neither an alias ({', '.join(ALIASES)}) nor an existing path"
        )
    try:
        return load_risk_model(p), str(p)
    except RiskModelError as exc:
        raise CliError(str(exc)) from None


# ============================================================================ fuse


def fuse_arrays(
    net: Any, m1: np.ndarray, m2: np.ndarray, pose1: np.ndarray, pose2: np.ndarray, cell: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Prealign map 2 into map 1's frame by the poses, run the network.

    Returns ``(m (2,H,W), u (H,W), m2_prealigned (2,H,W), rel_pose (3,))``, float32 masses.
    """
    from traffictwin.fusion.model_io import predict_masses
    from traffictwin.fusion.pairs import prealign
    from traffictwin.grid import GridSpec

    grid = GridSpec(rows=m1.shape[1], cols=m1.shape[2], cell=cell)
    m2w, rel = prealign(m2, pose1, pose2, grid)
    x = np.concatenate([m1, m2w])[None].astype(np.float32)
    m, u = predict_masses(net, x, batch_size=1)
    return m[0], u[0], m2w, rel


def mass_panels(panels: list[tuple[np.ndarray, np.ndarray | None]]) -> np.ndarray:
    """BGR uint8 image of mass maps side by side, white separators, upscaled to ~384 px tall:
    each panel ``(masses (2, H, W), u (H, W) or None = 1 - m_free - m_occ)``; the report's colour
    map (:mod:`traffictwin.report.colours`: green = free, red = occupied, grey = unknown)."""
    from traffictwin.report.colours import masses_to_bgr8

    h = panels[0][0].shape[1]
    sep = np.full((h, 4, 3), 255, np.uint8)
    parts = []
    for k, (mm, uu) in enumerate(panels):
        parts += [masses_to_bgr8(mm, uu)]
        parts += [sep] if k < len(panels) - 1 else []
    img = np.concatenate(parts, axis=1)
    scale = max(1, int(round(384 / h)))
    return np.repeat(np.repeat(img, scale, axis=0), scale, axis=1) if scale > 1 else img


def preview_image(m1: np.ndarray, m2w: np.ndarray, m: np.ndarray, u: np.ndarray) -> np.ndarray:
    """BGR uint8 preview: map 1 | map 2 prealigned | fused (:func:`mass_panels`)."""
    return mass_panels([(m1, None), (m2w, None), (m, u)])


def cmd_fuse(args: argparse.Namespace) -> int:
    import cv2

    from traffictwin.io.atomic import atomic_path

    pose1 = parse_pose(args.pose1, "--pose1")
    pose2 = parse_pose(args.pose2, "--pose2")
    m1, c1 = load_masses(args.map1)
    m2, c2 = load_masses(args.map2)
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
    if args.cell is not None and not (args.cell > 0 and math.isfinite(args.cell)):
        raise CliError(f"--cell: must be a positive number of metres, got {args.cell}")
    out = Path(args.output)
    base = out.with_suffix("") if out.suffix == ".npz" else out
    npz_path, png_path = base.with_name(base.name + ".npz"), base.with_name(base.name + ".png")
    if not base.parent.exists():
        raise CliError(f"-o: output folder {base.parent} does not exist")
    net, train_grid, desc = load_fusion(args.model, args.config)
    cell = (
        args.cell if args.cell is not None else (c1 if c1 is not None else train_grid.get("cell"))
    )
    if cell is None:
        raise CliError(
            "grid cell size unknown: pass --cell (m per cell) or store 'cell' in the .npz"
        )
    if "cell" in train_grid and abs(float(train_grid["cell"]) - cell) > 1e-9:
        raise CliError(
            f"maps have {cell} m cells but the model ({desc}) was trained on {train_grid['cell']} m cells"
        )
    t0 = time.perf_counter()
    m, u, m2w, rel = fuse_arrays(net, m1, m2, pose1, pose2, cell)
    ms = (time.perf_counter() - t0) * 1e3
    preview = preview_image(m1, m2w, m, u)
    ok, png = cv2.imencode(".png", preview)
    if not ok:
        raise CliError("could not encode the PNG preview")
    buf = io.BytesIO()
    np.savez_compressed(
        buf,
        m_free=m[0],
        m_occ=m[1],
        u=u,
        pose1=pose1,
        pose2=pose2,
        rel_pose=rel,
        cell=np.float64(cell),
    )
    with atomic_path(npz_path, suffix=".npz") as t1, atomic_path(png_path, suffix=".png") as t2:
        t1.write_bytes(buf.getvalue())
        t2.write_bytes(png.tobytes())
    summary = {
        "output": str(npz_path),
        "preview": str(png_path),
        "model": desc,
        "grid": [h, w],
        "cell_m": cell,
        "rel_pose": [float(v) for v in rel],
        "fuse_ms": round(ms, 2),
        "mean_u": float(u.mean()),
        "occupied_cells": int(((m[1] + u / 2) > 0.5).sum()),
    }
    print(json.dumps(json_safe(summary), indent=2))
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
    """BGR uint8 preview: the twin | each vehicle's map where the twin put it (:func:`mass_panels`;
    a left-out map is all zeros: blue = unknown)."""
    return mass_panels([(twin, None), *((c, None) for c in contributions)])


def cmd_twin(args: argparse.Namespace) -> int:
    import cv2

    from traffictwin.evidential.warp import warp_masses
    from traffictwin.grid import GridSpec
    from traffictwin.io.atomic import atomic_path
    from traffictwin.sim.scene import relative_pose
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
    out = Path(args.output)
    base = out.with_suffix("") if out.suffix == ".npz" else out
    npz_path, png_path = base.with_name(base.name + ".npz"), base.with_name(base.name + ".png")
    if not base.parent.exists():
        raise CliError(f"-o: output folder {base.parent} does not exist")
    inputs = {Path(m).resolve() for m in args.maps}
    if npz_path.resolve() in inputs or png_path.resolve() in inputs:
        raise CliError(f"-o: {base} would overwrite an input map")
    models = load_twin_models(args.method, args.registration_model, args.fusion_model)
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
    ok, png = cv2.imencode(".png", twin_preview(step.masses, contributions))
    if not ok:
        raise CliError("could not encode the PNG preview")
    u = 1.0 - step.masses[0] - step.masses[1]
    buf = io.BytesIO()
    np.savez_compressed(
        buf,
        m_free=step.masses[0],
        m_occ=step.masses[1],
        u=u.astype(np.float32),
        used=step.used,
        accepted=step.accepted,
        rel_pose_used=step.poses,
        rel_pose_given=rel,
        cell=np.float64(cell),
    )
    with atomic_path(npz_path, suffix=".npz") as t1, atomic_path(png_path, suffix=".png") as t2:
        t1.write_bytes(buf.getvalue())
        t2.write_bytes(png.tobytes())
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
    print(json.dumps(json_safe(summary), indent=2))
    return 0


# ============================================================================ risk


@dataclass
class StereoSettings:
    sgm: dict[str, Any]
    orb: dict[str, Any]
    source: str


def stereo_settings(
    domain: Any, params_path: str | None, model_desc: str = "the model"
) -> StereoSettings:
    """SGM/ORB settings the risk data were made with.

    ``domain.sgm`` / ``domain.orb`` of the model's metadata if present; else ``risk_data.sgm`` /
    ``risk_data.orb`` of the params file ``params_path`` the user passed; else the library
    defaults."""
    if isinstance(domain, dict) and (
        isinstance(domain.get("sgm"), dict) or isinstance(domain.get("orb"), dict)
    ):
        return StereoSettings(
            dict(domain.get("sgm") or {}),
            dict(domain.get("orb") or {}),
            f"metadata of {model_desc}",
        )
    if params_path:
        import yaml

        path = Path(params_path)
        if not path.is_file():
            raise CliError(f"--params: {path} not found")
        try:
            cfg = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as exc:
            raise CliError(f"{path}: not valid YAML ({exc})") from None
        rd = cfg.get("risk_data") or {} if isinstance(cfg, dict) else {}
        if isinstance(rd.get("sgm"), dict) or isinstance(rd.get("orb"), dict):
            return StereoSettings(dict(rd.get("sgm") or {}), dict(rd.get("orb") or {}), str(path))
    return StereoSettings({}, {}, "library defaults")


def risk_one(
    rmodel: Any,
    left: np.ndarray,
    right: np.ndarray,
    speed: float | None,
    st: StereoSettings,
    thw_threshold: float,
) -> dict[str, Any]:
    """ORB verdict, SGM disparity, predicted risk and THW verdict of one pair (see :func:`risk_verdict`)."""
    from traffictwin.stereo.orb import check_pair
    from traffictwin.stereo.sgm import compute_disparity

    t0 = time.perf_counter()
    orb = check_pair(left, right, **st.orb)
    t1 = time.perf_counter()
    disp = compute_disparity(left, right, **st.sgm)
    t2 = time.perf_counter()
    sp = None if speed is None else np.array([speed], np.float32)
    risk = float(
        rmodel.predict(
            left_bgr=left[None], disp_sgm=disp[None], disp_gt=None, speed=sp, batch_size=1
        )[0]
    )
    t3 = time.perf_counter()
    valid = disp >= 0
    out = {
        "orb_outlier": bool(orb.outlier),
        "orb_verdict": "unreliable pair" if orb.outlier else "ok",
        "orb_n_matches": int(orb.n_matches),
        "orb_n_reliable": int(orb.n_reliable),
        "orb_mean_dx": float(orb.mean_dx),
        "orb_mean_dy": float(orb.mean_dy),
        "disp_valid_fraction": float(valid.mean()),
        "disp_median_px": float(np.median(disp[valid])) if valid.any() else float("nan"),
        **risk_verdict(risk, speed, thw_threshold),
        "orb_ms": round((t1 - t0) * 1e3, 2),
        "sgm_ms": round((t2 - t1) * 1e3, 2),
        "model_ms": round((t3 - t2) * 1e3, 2),
    }
    return out


def risk_verdict(
    risk: float, speed: float | None, thw_threshold: float = CRITICAL_THW
) -> dict[str, Any]:
    """THW from the normalised risk (``risk = min(1/THW, 20)/20`` ⇒ ``THW = 1/(20 risk)``; risk <= 0:
    no vehicle ahead, THW = inf) and the verdict ``critical`` iff THW < ``thw_threshold`` (s).
    With ``speed`` (m/s) the implied free distance ``THW * speed`` (m) is added."""
    thw = float(risk_to_thw(np.asarray(risk), cap=math.inf))
    out: dict[str, Any] = {
        "risk": risk,
        "thw_s": thw,
        "thw_threshold_s": thw_threshold,
        "critical": bool(thw < thw_threshold),
        "verdict": "critical" if thw < thw_threshold else "uncritical",
    }
    if speed is not None:
        out["speed_m_s"] = float(speed)
        out["gap_m"] = thw * speed if math.isfinite(thw) else math.inf
    return out


def cmd_risk(args: argparse.Namespace) -> int:
    from traffictwin.io.atomic import write_json_atomic, write_text_atomic

    if args.speed is not None and not (math.isfinite(args.speed) and args.speed >= 0):
        raise CliError(f"--speed: must be a finite speed >= 0 m/s, got {args.speed}")
    if not args.thw_threshold > 0:
        raise CliError(f"--thw-threshold: must be > 0 s, got {args.thw_threshold}")
    src = Path(args.left)
    if src.is_dir():
        if args.right is not None:
            raise CliError(
                f"{src} is a folder: pass no RIGHT image (pairs are found by *_left/*_right names)"
            )
        pairs = find_pairs(src)
    else:
        if args.right is None:
            raise CliError(
                f"{src}: pass LEFT and RIGHT images, or a folder of <id>_left/<id>_right pairs"
            )
        pairs = [(src.stem, src, Path(args.right))]
    images = []
    for pid, lp, rp in pairs:  # read + validate everything before any work or output
        left, right = read_image(lp), read_image(rp)
        if left.shape != right.shape:
            raise CliError(
                f"{rp}: size {right.shape[1]}x{right.shape[0]} differs from {lp}'s {left.shape[1]}x{left.shape[0]} (W x H)"
            )
        images.append((pid, lp, rp, left, right))
    rmodel, desc = load_risk(args.model)
    if rmodel.cfg.use_speed and args.speed is None:
        raise CliError(f"the model ({desc}) uses the subject speed: pass --speed (m/s)")
    st = stereo_settings(rmodel.meta.get("domain"), args.params, desc)
    rows = []
    for pid, lp, rp, left, right in images:
        r = risk_one(rmodel, left, right, args.speed, st, args.thw_threshold)
        rows.append({"id": pid, "left": str(lp), "right": str(rp), **r})
    if src.is_dir():
        cols = list(rows[0])
        buf = io.StringIO()
        wr = csv.DictWriter(buf, fieldnames=cols, lineterminator="\n")
        wr.writeheader()
        wr.writerows(rows)
        if args.output:
            write_text_atomic(args.output, buf.getvalue())
            print(
                f"{len(rows)} pair(s) -> {args.output} (model {desc}; stereo settings: {st.source})"
            )
        else:
            sys.stdout.write(buf.getvalue())
    else:
        res = json_safe({**rows[0], "model": desc, "stereo_settings": st.source})
        if args.output:
            write_json_atomic(args.output, res)
        print(json.dumps(res, indent=2, default=str))
    return 0


# ============================================================================ registry / runs


def cmd_rollback(args: argparse.Namespace) -> int:
    from traffictwin.mlops import registry as reg

    cl = _registry_client()
    log_path = Path(args.log) if args.log else reg.promotion_log(cl, args.model)
    try:
        with reg.gate_lock(
            reg.default_lock_path()
        ):  # never between a gate's decision and its apply
            rec = reg.rollback(cl, args.model, args.version, log_path=log_path)
    except reg.RegistryError as exc:
        raise CliError(str(exc)) from None
    print(f"{rec['name']}: champion v{rec['from_version']} -> v{rec['to_version']}")
    if log_path is None:
        print("(no promotion log recorded for this model: pass --log FILE to log the rollback)")
    return 0


def cmd_status(args: argparse.Namespace) -> int:
    from traffictwin.mlops import registry as reg

    cl = _registry_client()
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
    from traffictwin.mlops.runs import RunsError, compare_runs, format_runs

    try:
        df = compare_runs(args.experiment, metrics=args.metrics, uri=args.uri)
    except RunsError as exc:
        raise CliError(str(exc)) from None
    if args.csv:
        from traffictwin.io.atomic import write_text_atomic

        write_text_atomic(args.csv, df.to_csv(index=False))
    print(format_runs(df, wide=args.wide))
    return 0


# ============================================================================ parser


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="traffictwin",
        description="traffictwin: cooperative OGM fusion and stereo risk — inference, registry, runs.",
    )
    ap.add_argument(
        "--threads",
        type=int,
        default=None,
        help="torch CPU threads (default: torch's choice; 1 is fastest for single items on a busy machine)",
    )
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")

    f = sub.add_parser(
        "fuse",
        help="fuse two evidential grid maps with the fusion network",
        description="Prealign MAP2 into MAP1's frame by the poses and fuse them with the network.",
    )
    f.add_argument("map1", help=".npz with m_free, m_occ (H, W) float32 masses, ego map")
    f.add_argument("map2", help=".npz of the other vehicle's map, same size")
    f.add_argument(
        "--pose1", required=True, help="x,y,yaw of map 1's sensor in the world (m, m, rad)"
    )
    f.add_argument(
        "--pose2", required=True, help="x,y,yaw of map 2's sensor in the world (m, m, rad)"
    )
    f.add_argument(
        "--model",
        default="champion",
        help="champion | challenger (registry) or a model folder/.ckpt (default champion)",
    )
    f.add_argument(
        "--config",
        default=None,
        help="pose-noise configuration of the registered model traffictwin-fusion-<config> "
        "(default: the only registered fusion model)",
    )
    f.add_argument(
        "--cell",
        type=float,
        default=None,
        help="m per cell (default: the .npz 'cell', else the model's)",
    )
    f.add_argument(
        "-o", "--output", required=True, help="output base name: writes OUT.npz and OUT.png"
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
    tw.add_argument(
        "-o", "--output", required=True, help="output base name: writes OUT.npz and OUT.png"
    )
    tw.set_defaults(func=cmd_twin)

    r = sub.add_parser(
        "risk",
        help="stereo risk: ORB check, SGM disparity, predicted risk and THW verdict",
        description="LEFT RIGHT images, or a FOLDER of <id>_left.png/<id>_right.png pairs (-> CSV).",
    )
    r.add_argument("left", help="left image, or a folder of pairs")
    r.add_argument("right", nargs="?", default=None, help="right image (omit for a folder)")
    r.add_argument(
        "--speed",
        type=float,
        default=None,
        help="subject speed (m/s): gap = THW * speed; required by speed models",
    )
    r.add_argument(
        "--model",
        default="champion",
        help="champion | challenger (registry traffictwin-risk) or a model folder",
    )
    r.add_argument(
        "--thw-threshold",
        type=float,
        default=CRITICAL_THW,
        help=f"critical if THW below this (s), default {CRITICAL_THW}",
    )
    r.add_argument(
        "--params",
        default=None,
        help="params file with risk_data.sgm/orb, used when the model's metadata has no "
        "domain.sgm/orb (default: the library's SGM/ORB defaults)",
    )
    r.add_argument(
        "-o",
        "--output",
        default=None,
        help="write the JSON (pair) or CSV (folder) here (default: stdout)",
    )
    r.set_defaults(func=cmd_risk)

    b = sub.add_parser(
        "rollback", help="move the champion alias back (previous champion or --version)"
    )
    b.add_argument(
        "--model", required=True, help="registered model name, e.g. traffictwin-fusion-D"
    )
    b.add_argument(
        "--version", default=None, help="version to make champion (default: the previous champion)"
    )
    b.add_argument(
        "--log",
        default=None,
        help="promotion log to append to (default: the one the gate recorded on the model)",
    )
    b.set_defaults(func=cmd_rollback)

    s = sub.add_parser("status", help="champion / challenger of the registered models")
    s.add_argument(
        "--model",
        nargs="+",
        default=None,
        help="registered model names (default: all traffictwin-*)",
    )
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_status)

    ru = sub.add_parser("runs", help="MLflow runs")
    rsub = ru.add_subparsers(dest="runs_command", required=True, metavar="SUBCOMMAND")
    c = rsub.add_parser("compare", help="compare the runs of an experiment as a table")
    c.add_argument("--experiment", required=True, help="MLflow experiment (fusion | risk | ...)")
    c.add_argument("--metrics", nargs="+", default=None, help="metric names (default: all)")
    c.add_argument(
        "--uri",
        default=None,
        help="tracking URI (default: MLFLOW_TRACKING_URI or the project's mlflow.db)",
    )
    c.add_argument("--wide", action="store_true", help="full run ids and every tag column")
    c.add_argument("--csv", default=None, help="also write the table as CSV")
    c.set_defaults(func=cmd_runs_compare)
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.threads is not None:
        if args.threads < 1:
            parser.error(f"--threads must be >= 1, got {args.threads}")
        import torch

        torch.set_num_threads(args.threads)
    try:
        rc = args.func(args)
    except CliError as exc:
        print(f"traffictwin {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    return int(rc or 0)


if __name__ == "__main__":
    sys.exit(main())
