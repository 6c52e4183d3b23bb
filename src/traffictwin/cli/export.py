"""``traffictwin export fusion|risk``: a network traced on an input of its training shape and
saved as TorchScript (:mod:`traffictwin.export`)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from traffictwin import __version__
from traffictwin.io.outputs import OutputSet

from .common import CliError, add_arguments, arg, model_options, output_options

HELP = "export a fusion or risk network as TorchScript"
DESCRIPTION = (
    "Trace the network on an input of its training shape and save it with torch.jit "
    "(loads with torch.jit.load alone; see traffictwin.export for the input/output layout)."
)
ARGUMENTS = [
    arg("problem", choices=("fusion", "risk")),
    *model_options("model to export", "traffictwin-fusion / traffictwin-risk"),
    *output_options("the TorchScript file to write (e.g. fusion.pt)"),
]


def add_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help=HELP, description=DESCRIPTION)
    add_arguments(p, ARGUMENTS)
    p.set_defaults(func=cmd_export)


def cmd_export(args: argparse.Namespace) -> int:
    from traffictwin import api

    out = Path(args.output)
    with OutputSet([args.output], kinds="export", force=args.force) as outs:  # "" is refused
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
