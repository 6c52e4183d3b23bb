"""``traffictwin disparity``: the disparity map (px, float32) and its confidence of one rectified
LEFT RIGHT pair, from OpenCV SGM or the learned stereo network, after the checks of
``traffictwin risk`` (readable images of equal size, the ORB pair check)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from traffictwin.io.jsonio import json_clean
from traffictwin.io.outputs import OutputSet

from .common import CliError, add_arguments, arg, output_options, uri_option

#: exit status when the pair failed the stereo pair check (the maps are written, not trusted)
EXIT_UNRELIABLE = 3

HELP = "disparity map (px) and its confidence of a rectified stereo pair (SGM or learned)"
DESCRIPTION = (
    "Writes OUT.npz with 'disparity' (H, W) float32 px (-1 where invalid) and 'confidence' "
    "(H, W) float32 in [0, 1] (0 invalid; SGM: 1 on every valid pixel; learned: 1 - spread / "
    "the spread threshold calibrated on validation), and prints a JSON summary. The pair gets "
    "the ORB check of traffictwin risk first. Exit status: 0 the pair passed its check, "
    f"{EXIT_UNRELIABLE} it failed (the maps are written but not to be trusted), 1 an error."
)
ARGUMENTS = [
    arg("left", help="left image of a rectified pair"),
    arg("right", help="right image of the same pair"),
    arg(
        "--model",
        default="sgm",
        help="'sgm' (OpenCV SGM, the default), the learned stereo network's registry reference "
        "(traffictwin-stereo@champion, or champion | challenger) or its folder "
        "(e.g. models/stereo/learned)",
    ),
    *uri_option(),
    arg(
        "--params",
        default=None,
        help="params file with risk_data.sgm/orb (SGM and pair-check settings; default: the "
        "library's)",
    ),
    *output_options("the .npz to write (disparity, confidence)"),
]


def add_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("disparity", help=HELP, description=DESCRIPTION)
    add_arguments(p, ARGUMENTS)
    p.set_defaults(func=cmd_disparity)


def cmd_disparity(args: argparse.Namespace) -> int:
    from traffictwin import api
    from traffictwin.io.npz import write_npz_deterministic

    if not args.output:
        raise CliError("-o: the output path is empty; expected a .npz file name")
    out = Path(args.output)
    if out.suffix.lower() != ".npz":
        raise CliError(f"-o: {out} must end in .npz (the disparity and confidence arrays)")
    left, right = Path(args.left), Path(args.right)
    inputs = [left, right] + [Path(p) for p in (args.params,) if p]
    if args.model != api.stereo.SGM and Path(args.model).exists():
        inputs.append(Path(args.model))
    outs = OutputSet([out], kinds="disparity", inputs=inputs, force=args.force)
    for p in (left, right):  # headers before the network (and torch) loads
        api.check_image_file(p)
    stereo = api.load_stereo(args.model, tracking_uri=args.tracking_uri)
    res = api.disparity_of_pair(stereo, left, right, params_path=args.params)
    with outs:
        arrays = {"disparity": res.disparity, "confidence": res.confidence}
        write_npz_deterministic(outs.temp_path(out), arrays, compresslevel=1)
        outs.commit()
    valid = res.disparity >= 0
    summary = {
        "left": str(left),
        "right": str(right),
        "output": str(out),
        "source": res.source,
        "model": stereo.description,
        "height": int(res.disparity.shape[0]),
        "width": int(res.disparity.shape[1]),
        "valid_fraction": float(valid.mean()),
        "median_disparity_px": float(np.median(res.disparity[valid])) if valid.any() else None,
        **res.check,
    }
    print(json.dumps(json_clean(summary), indent=2))
    if not res.reliable:
        print(
            f"traffictwin disparity: warning: {left}: the pair failed its check "
            f"({res.check['orb_reason']}); the maps are written but not to be trusted",
            file=sys.stderr,
        )
        return EXIT_UNRELIABLE
    return 0
