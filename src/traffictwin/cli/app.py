"""The ``traffictwin`` parser, built from the subcommand modules in the order of ``--help``, and
:func:`main`: parse, set the process-wide defaults (HTTP retries, OpenMP waiting, threads), run
the subcommand with one-line errors (:func:`traffictwin.cli.common.run_command`)."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence

from traffictwin import __version__
from traffictwin.api import HTTP_ENV
from traffictwin.threads import passive_omp_wait, pin_threads

from .common import run_command
from .disparity import add_parsers as add_disparity
from .export import add_parsers as add_export
from .fuse import add_parsers as add_fuse
from .registry import add_parsers as add_registry
from .risk import add_parsers as add_risk
from .runs import add_parsers as add_runs
from .twin import add_parsers as add_twin

#: each subcommand module's parser builder, in the order of ``traffictwin --help``
COMMANDS = (add_fuse, add_twin, add_risk, add_disparity, add_export, add_registry, add_runs)


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
    for add_parsers in COMMANDS:
        add_parsers(sub)
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``traffictwin``; its exit status (Ctrl-C anywhere: one line and 130, no traceback)."""
    try:
        return _main(argv)
    except KeyboardInterrupt:
        print("traffictwin: interrupted (Ctrl-C)", file=sys.stderr)
        return 130


def _main(argv: Sequence[str] | None) -> int:
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
    return run_command(args.func, args)
