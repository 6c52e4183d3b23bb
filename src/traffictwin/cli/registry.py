"""``traffictwin rollback`` and ``traffictwin status``: the champion / challenger aliases of the
registered models (promotion itself is the repository's workflow, ``python -m pipelines.promote``)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from traffictwin.mlops.uris import mask_secrets

from .common import CliError, add_arguments, arg, uri_option

ROLLBACK_ARGUMENTS = [
    arg("--model", required=True, help="registered model name, e.g. traffictwin-fusion"),
    arg(
        "--version", default=None, help="version to make champion (default: the previous champion)"
    ),
    arg(
        "--log",
        default=None,
        help="promotion log to append to (default: the one the gate recorded on the model)",
    ),
    *uri_option(),
]
STATUS_ARGUMENTS = [
    arg(
        "--model",
        nargs="+",
        default=None,
        help="registered model names (default: all traffictwin-*)",
    ),
    arg("--json", action="store_true"),
    *uri_option(),
]


def add_parsers(sub: argparse._SubParsersAction) -> None:
    b = sub.add_parser(
        "rollback", help="move the champion alias back (previous champion or --version)"
    )
    add_arguments(b, ROLLBACK_ARGUMENTS)
    b.set_defaults(func=cmd_rollback)
    s = sub.add_parser("status", help="champion / challenger of the registered models")
    add_arguments(s, STATUS_ARGUMENTS)
    s.set_defaults(func=cmd_status)


def _registry_client(args: argparse.Namespace):
    from traffictwin import api

    try:
        return api.connect(getattr(args, "tracking_uri", None))
    except Exception as exc:  # noqa: BLE001 - one masked line (the URI's password never printed)
        raise CliError(mask_secrets(" ".join(str(exc).split()))) from None


def cmd_rollback(args: argparse.Namespace) -> int:
    from traffictwin.mlops import registry as reg

    cl = _registry_client(args)
    log_path = Path(args.log) if args.log else reg.promotion_log(cl, args.model)
    try:
        # never between a gate's decision and its apply
        with reg.gate_lock(reg.default_lock_path(cl.tracking_uri)):
            rec = reg.rollback(cl, args.model, args.version, log_path=log_path)
    except reg.RegistryError as exc:
        raise CliError(mask_secrets(str(exc))) from None
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
    if args.model:
        known = set(reg.registered_names(cl))
        unknown = [n for n in names if n not in known]
        if unknown:
            raise CliError(
                f"--model: no registered model {', '.join(repr(n) for n in unknown)} "
                f"(registered: {', '.join(sorted(known)) or 'none'})"
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
