"""``traffictwin runs compare``: the MLflow runs of an experiment as a table (and a CSV)."""

from __future__ import annotations

import argparse

from traffictwin.io.outputs import OutputSet

from .common import CliError, add_arguments, arg

COMPARE_ARGUMENTS = [
    arg("--experiment", required=True, help="MLflow experiment (fusion | risk | ...)"),
    arg(
        "--metrics",
        nargs="+",
        default=None,
        help="metric names, e.g. val/kld_full test/kld_fou_mean (default: all)",
    ),
    arg(
        "--configuration",
        default=None,
        help="pick a per-configuration metric: test/kld_fou_mean means test/<CONFIGURATION>/kld_fou_mean "
        "(default: one column per configuration)",
    ),
    arg(
        "--tracking-uri",
        "--uri",
        dest="tracking_uri",
        default=None,
        help="tracking URI (default: MLFLOW_TRACKING_URI or the project's mlflow.db)",
    ),
    arg("--wide", action="store_true", help="full run ids and every tag column"),
    arg("--csv", default=None, help="also write the table as CSV"),
    arg(
        "--force",
        action="store_true",
        help="replace a previous --csv table of this command (never any other file)",
    ),
]


def add_parsers(sub: argparse._SubParsersAction) -> None:
    ru = sub.add_parser("runs", help="MLflow runs")
    rsub = ru.add_subparsers(dest="runs_command", required=True, metavar="SUBCOMMAND")
    c = rsub.add_parser("compare", help="compare the runs of an experiment as a table")
    add_arguments(c, COMPARE_ARGUMENTS)
    c.set_defaults(func=cmd_runs_compare)


def cmd_runs_compare(args: argparse.Namespace) -> int:
    from traffictwin import api
    from traffictwin.mlops.runs import RunsError, compare_runs, format_runs

    outs = OutputSet(
        [] if args.csv is None else [args.csv], kinds="runs-csv", force=args.force, option="--csv"
    )
    uri = api.resolve_tracking_uri(args.tracking_uri)
    try:
        df = compare_runs(
            args.experiment, metrics=args.metrics, uri=uri, configuration=args.configuration
        )
    except RunsError as exc:
        raise CliError(str(exc)) from None
    if args.csv is not None:
        with outs:
            outs.write_text(args.csv, df.to_csv(index=False))
            outs.commit()
    print(format_runs(df, wide=args.wide))
    return 0
