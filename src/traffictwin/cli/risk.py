"""``traffictwin risk``: the stereo risk of one LEFT RIGHT pair (JSON) or of a FOLDER of pairs
(CSV, streamed in batches): ORB check, SGM disparity, predicted risk and the THW verdict."""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from traffictwin.api import ApiWarning, StereoSettings
from traffictwin.io.jsonio import json_clean
from traffictwin.io.outputs import OutputSet
from traffictwin.risk.evaluation.scoring import PAPER

from .common import CliError, add_arguments, arg, csv_value, model_options, output_options

#: exit status when some pair failed the stereo pair check (its verdict is "unknown")
EXIT_UNKNOWN = 3

HELP = "stereo risk: ORB check, disparity (SGM, or the learned network the model reads), risk and THW verdict"
DESCRIPTION = (
    "LEFT RIGHT images, or a FOLDER of <id>_left.png/<id>_right.png pairs (-> CSV, streamed in "
    "batches). A pair that fails the ORB check gets verdict 'unknown' with the reason. Exit "
    f"status: 0 every pair has a verdict, {EXIT_UNKNOWN} some pair's verdict is unknown (the "
    "output is written), 1 an error, 130 interrupted."
)
ARGUMENTS = [
    arg("left", help="left image, or a folder of pairs"),
    arg("right", nargs="?", default=None, help="right image (omit for a folder)"),
    arg(
        "--speed",
        type=float,
        default=None,
        help="subject speed (m/s): gap = THW * speed; required by speed models, checked against the training range",
    ),
    *model_options("risk model", "traffictwin-risk"),
    arg(
        "--stereo-model",
        default=None,
        help="the learned stereo network's folder (e.g. models/stereo/learned) or registry "
        "reference (traffictwin-stereo@champion), for a risk model that reads its disparity "
        "(disp_learned) and does not package it in its folder's stereo/",
    ),
    arg(
        "--thw-threshold",
        type=float,
        default=PAPER["threshold_s"],
        help=f"critical if THW below this (s), default {PAPER['threshold_s']}",
    ),
    arg(
        "--params",
        default=None,
        help="params file with risk_data.sgm/orb/max_speed, used when the model's metadata lacks them",
    ),
    arg(
        "--resize",
        action="store_true",
        help="resize images to the model's training camera size before ORB/SGM (else a size mismatch is an error)",
    ),
    arg("--batch-size", type=int, default=16, help="frames per batch for a folder (default 16)"),
    *output_options("write the JSON (pair) or CSV (folder) here (default: stdout)", required=False),
]


def add_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("risk", help=HELP, description=DESCRIPTION)
    add_arguments(p, ARGUMENTS)
    p.set_defaults(func=cmd_risk)


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
    if args.output == "":
        raise CliError("-o: the output path is empty; expected a file name (or no -o: stdout)")
    out = Path(args.output) if args.output else None
    inputs = [p for f in frames for p in (f.left, f.right)] + [
        Path(p) for p in (args.params, args.stereo_model) if p
    ]
    kind = "risk-csv" if is_folder else "risk-json"
    outs = OutputSet([out] if out else [], kinds=kind, inputs=inputs, force=args.force)
    for f in frames:  # every image's header before the model (and torch) loads: a huge or
        for p in (f.left, f.right):  # broken image is refused in a fraction of a second
            api.check_image_file(p)
    rmodel = api.load_risk(
        args.model, tracking_uri=args.tracking_uri, stereo_model=args.stereo_model
    )
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
            dest = _RiskOutput(outs, out, paths, rmodel, st)
            unknown = (dest.folder if is_folder else dest.pair)(rows)
    if unknown:
        first, n = unknown[0], len(unknown)
        more = f" (and {n - 1} more pair(s))" if n > 1 else ""
        print(
            f"traffictwin risk: warning: no verdict for {first[0]}{more}: {first[1]}",
            file=sys.stderr,
        )
        return EXIT_UNKNOWN
    return 0


@dataclass(frozen=True)
class _RiskOutput:
    """Where and how ``traffictwin risk`` writes its rows: ``outs`` (``out``, None = stdout),
    each frame's image ``paths`` by id, the model and the stereo settings the rows came from."""

    outs: OutputSet
    out: Path | None
    paths: dict[str, tuple[str, str]]
    rmodel: Any
    st: StereoSettings

    def labelled(self, row: dict[str, Any]) -> dict[str, Any]:
        """``row`` after its id and its left / right image paths."""
        lp, rp = self.paths[row["id"]]
        return {"id": row["id"], "left": lp, "right": rp, **row}

    def pair(self, rows: Iterator[dict[str, Any]]) -> list[tuple[str, str]]:
        """One pair: its JSON on stdout, and into ``out`` if given; ``[(left image, why)]`` if
        its verdict is unknown, else ``[]``."""
        row = next(rows)
        from traffictwin.api import answered_by

        res = json_clean({**self.labelled(row), **answered_by(self.rmodel, self.st)})
        if self.out:
            self.outs.write_text(self.out, json.dumps(res, indent=2, sort_keys=True) + "\n")
            self.outs.commit()
        print(json.dumps(res, indent=2))
        return _unknown(self.labelled(row))

    def folder(self, rows: Iterator[dict[str, Any]]) -> list[tuple[str, str]]:
        """A folder of pairs: one CSV row per pair as each batch comes, into ``out`` or stdout;
        ``[(left image, why)]`` of the pairs whose verdict is unknown."""
        out = self.out
        fh = self.outs.open(out, "w", newline="") if out else sys.stdout
        unknown: list[tuple[str, str]] = []
        try:
            wr = None
            n = 0
            for row in rows:
                row = self.labelled(row)
                unknown += _unknown(row)
                if wr is None:
                    wr = csv.DictWriter(fh, fieldnames=list(row), lineterminator="\n")
                    wr.writeheader()
                wr.writerow({k: csv_value(v) for k, v in row.items()})
                n += 1
        finally:
            if out:
                fh.close()
        if out:
            self.outs.commit()
            print(
                f"{n} pair(s) -> {out} (model {self.rmodel.description}, "
                f"predictor {self.rmodel.predictor}; stereo settings: {self.st.source}; "
                f"{len(unknown)} without a verdict)"
            )
        return unknown


def _unknown(row: dict[str, Any]) -> list[tuple[str, str]]:
    """``[(left image, why)]`` when ``row``'s verdict is unknown (the pair failed its check)."""
    from traffictwin.api.risk import UNKNOWN

    return [(row["left"], row["verdict_reason"])] if row["verdict"] == UNKNOWN else []
