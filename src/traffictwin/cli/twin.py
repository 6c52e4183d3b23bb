"""``traffictwin twin``: N vehicles' evidential grid maps registered onto the first and combined
into one twin (:mod:`traffictwin.twin.fuse`); a map whose registration is rejected is left out."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from traffictwin.io.jsonio import json_clean
from traffictwin.io.outputs import OutputSet

from .common import (
    CliError,
    add_arguments,
    arg,
    load_masses,
    npz_bytes,
    npz_png,
    output_options,
    parse_pose,
    png_bytes,
    positive_cell,
)
from .previews import twin_preview

HELP = "fuse N vehicles' evidential grid maps into one twin in the first map's frame"
DESCRIPTION = (
    "Register every map onto the first (the reference vehicle's) from the given poses and "
    "combine them (traffictwin.twin.fuse); a map whose registration is rejected is left out and reported."
)
METHODS = ("naive", "registered", "learned", "dnn", "registered+network", "learned+network")
ARGUMENTS = [
    arg(
        "maps", nargs="+", help=".npz maps (m_free, m_occ; same format as `fuse`), reference first"
    ),
    arg(
        "--pose",
        action="append",
        help="x,y,yaw of a map's sensor in a common world frame (m, m, rad); once per map, in order",
    ),
    arg(
        "--method",
        default="registered",
        choices=METHODS,
        help="pose source + combination (default registered: classical registration + Dempster, no model needed)",
    ),
    arg("--strategy", default="reference", choices=("reference", "sequential")),
    arg(
        "--registration-model",
        default=None,
        help="learned registration folder/.ckpt (methods learned*)",
    ),
    arg(
        "--fusion-model", default=None, help="fusion network folder/.ckpt (methods dnn, *+network)"
    ),
    arg("--cell", type=float, default=None, help="m per cell (default: the .npz 'cell')"),
    *output_options("output base name: writes OUT.npz and OUT.png"),
]


def add_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("twin", help=HELP, description=DESCRIPTION)
    add_arguments(p, ARGUMENTS)
    p.set_defaults(func=cmd_twin)


def load_twin_models(
    method: str, registration_model: str | None, fusion_model: str | None
) -> dict[str, Any]:
    """The models a twin method needs, from model folders/checkpoints (``--registration-model``:
    a learned registration, ``models/registration/<cfg>``; ``--fusion-model``: a fusion network)."""
    from traffictwin.fusion.model_io import FusionModelError, load_fusion_model
    from traffictwin.fusion.registration_io import load_registration_model
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


def _read_maps(args: argparse.Namespace) -> tuple[list[np.ndarray], np.ndarray, float]:
    """The world poses, the maps ``(N, 2, H, W)`` and the cell size (m), checked to agree."""
    if len(args.maps) < 2:
        raise CliError(f"maps: a twin needs at least two maps, got {len(args.maps)}")
    poses = args.pose or []
    if len(poses) != len(args.maps):
        raise CliError(
            f"--pose: give one x,y,yaw per map in the same order ({len(args.maps)} maps, {len(poses)} poses)"
        )
    world = [parse_pose(p, f"--pose #{k + 1} ({args.maps[k]})") for k, p in enumerate(poses)]
    loaded = [load_masses(m) for m in args.maps]
    from traffictwin.fusion.config import NETWORK_STRIDE

    for path, (m, _) in zip(args.maps, loaded):  # before any registration, warp or preview
        if min(m.shape[1:]) < NETWORK_STRIDE:
            raise CliError(
                f"{path}: grid of {m.shape[1]}x{m.shape[2]} cells (rows x cols); a twin's maps need "
                f"at least {NETWORK_STRIDE} cells along each side"
            )
    ref_m, ref_c = loaded[0]
    for path, (m, c) in zip(args.maps[1:], loaded[1:]):
        if m.shape != ref_m.shape:
            raise CliError(
                f"{path}: grid size {m.shape[1:]} differs from {args.maps[0]}'s {ref_m.shape[1:]} (rows, cols)"
            )
        if c is not None and ref_c is not None and abs(c - ref_c) > 1e-9:
            raise CliError(f"{path}: cell size {c} m differs from {args.maps[0]}'s {ref_c} m")
    cells = {c for _, c in loaded if c is not None}
    positive_cell(args.cell)
    if args.cell is not None and cells and abs(args.cell - next(iter(cells))) > 1e-9:
        raise CliError(
            f"--cell: {args.cell} m contradicts the maps' own cell size {next(iter(cells))} m"
        )
    cell = args.cell if args.cell is not None else (next(iter(cells)) if cells else None)
    if cell is None:
        raise CliError(
            "grid cell size unknown: pass --cell (m per cell) or store 'cell' in the .npz files"
        )
    return world, np.stack([m for m, _ in loaded]), cell


def _check_model_grids(
    args: argparse.Namespace, models: dict[str, Any], shape: tuple[int, int], cell: float
) -> None:
    """The networks run only on the grid they were trained on."""
    from traffictwin import api

    for need, net in models.items():
        meta = dict(getattr(net, "meta", {}) or {})
        opt = "--fusion-model" if need == "fusion" else "--registration-model"
        desc = f"{opt} {args.fusion_model if need == 'fusion' else args.registration_model}"
        api.check_fusion_domain(
            api.FusionModel(net, meta, dict(meta.get("grid") or {}), desc),
            shape,
            cell,
            str(args.maps[0]),
        )


def cmd_twin(args: argparse.Namespace) -> int:
    from traffictwin.evidential.warp import warp_masses
    from traffictwin.geometry import relative_pose
    from traffictwin.grid import GridSpec
    from traffictwin.twin.fuse import TwinInputError, TwinOptions, build_twin

    world, maps, cell = _read_maps(args)
    models = load_twin_models(args.method, args.registration_model, args.fusion_model)
    _check_model_grids(args, models, tuple(maps.shape[2:]), cell)
    npz_path, png_path = npz_png(args.output)
    outs = OutputSet([npz_path, png_path], inputs=args.maps, force=args.force)
    grid = GridSpec(rows=maps.shape[2], cols=maps.shape[3], cell=cell)
    rel = np.stack([np.zeros(3)] + [relative_pose(world[0], w) for w in world[1:]])
    try:
        options = TwinOptions(args.method, strategy=args.strategy, models=models)
        step = build_twin(maps, rel, grid, options)
    except TwinInputError as exc:
        raise CliError(str(exc)) from None
    contributions = [maps[0]] + [
        warp_masses(maps[k], step.poses[k], grid) if step.used[k] else np.zeros_like(maps[k])
        for k in range(1, len(maps))
    ]
    png = png_bytes(twin_preview(step.masses, contributions, cell=cell))
    u = 1.0 - step.masses[0] - step.masses[1]
    data = npz_bytes(
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
