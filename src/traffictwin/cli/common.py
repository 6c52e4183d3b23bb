"""What the ``traffictwin`` subcommands share: the one error type and its wording in CLI terms,
the option rows declared once (``--model``, ``--tracking-uri``, ``-o``/``--force``) and the table
helper that adds them, input parsing (poses, grid maps), output encoding (PNG, ``.npz``, CSV
cells) and running a command with one-line errors and warnings."""

from __future__ import annotations

import argparse
import io
import math
import os
import sys
import warnings
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np

from traffictwin.api import ApiError, ApiWarning
from traffictwin.io.outputs import OutputError, mark_png

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


# ============================================================================ inputs and outputs


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


def positive_cell(cell: float | None) -> None:
    """``--cell`` (or a list's ``cell``), if given, is a positive finite number of metres."""
    if cell is not None and not (cell > 0 and math.isfinite(cell)):
        raise CliError(f"--cell: must be a positive number of metres, got {cell}")


def npz_png(output: str, option: str = "-o") -> tuple[Path, Path]:
    """``OUT.npz`` and ``OUT.png`` of an output base name (with or without ``.npz``); an empty
    name, or one that names a folder (``dir/`` or an existing folder), is a :data:`CliError`."""
    if not output:
        raise CliError(f"{option}: the output name is empty; expected a base name such as out")
    if output.endswith(("/", os.sep)) or Path(output).is_dir():
        raise CliError(
            f"{option}: {output} is a folder; expected a base name for OUT.npz and OUT.png "
            f"(e.g. {Path(output) / 'out'})"
        )
    out = Path(output)
    base = out.with_suffix("") if out.suffix == ".npz" else out
    return base.with_name(base.name + ".npz"), base.with_name(base.name + ".png")


def png_bytes(img: np.ndarray) -> bytes:
    """``img`` as a PNG preview, marked as a ``traffictwin`` preview (:func:`mark_png`: so that
    ``--force`` replaces it, and no other PNG)."""
    import cv2

    ok, png = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 1])  # fast; PNG is lossless
    if not ok:
        raise CliError("could not encode the PNG preview")
    return mark_png(png.tobytes())


def npz_bytes(**arrays: Any) -> bytes:
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


# ============================================================================ option tables

#: one ``add_argument`` call: ``(flags, keyword arguments)``
Row = tuple[tuple[str, ...], dict[str, Any]]


def arg(*flags: str, **kwargs: Any) -> Row:
    """A row of an option table: the arguments of one ``parser.add_argument`` call."""
    return flags, kwargs


def add_arguments(p: argparse.ArgumentParser, rows: Iterable[Row]) -> None:
    """Add a table's rows to ``p`` in order (the order of ``--help``)."""
    for flags, kwargs in rows:
        p.add_argument(*flags, **kwargs)


def uri_option() -> list[Row]:
    return [
        arg(
            "--tracking-uri",
            default=None,
            help="MLflow tracking/registry URI (default: MLFLOW_TRACKING_URI, else the project's "
            "mlflow.db; a missing database is never created)",
        )
    ]


def model_options(what: str, registry: str) -> list[Row]:
    """``--model REF`` (registry reference, alias or model folder) and ``--tracking-uri``."""
    return [
        arg(
            "--model",
            default="champion",
            help=f"{what}: registry reference name@alias, or champion | challenger of {registry}, "
            "or a model folder (no registry needed); default champion",
        ),
        *uri_option(),
    ]


def output_options(help_text: str, required: bool = True) -> list[Row]:
    """``-o/--output`` and ``--force``."""
    return [
        arg("-o", "--output", required=required, default=None, help=help_text),
        arg(
            "--force",
            action="store_true",
            help="replace a previous output of this command's kind (never an input, a model "
            "folder, the MLflow store, a DVC file or output, src/ conf/ tests/ of a repository, "
            "a link, device or FIFO)",
        ),
    ]


# ============================================================================ running a command


def run_command(func: Callable[[argparse.Namespace], int], args: argparse.Namespace) -> int:
    """``func(args)``'s exit status; API warnings as one line each on stderr, and every error the
    user can cause as one line ``traffictwin CMD: error: ...`` and status 1; Ctrl-C is one line
    ``traffictwin CMD: interrupted ...`` and status 130 (unfinished outputs are discarded)."""
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
            rc = func(args)
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
        print(f"{prog}: interrupted (Ctrl-C)", file=sys.stderr)
        return 130
    finally:
        warnings.showwarning = show
    return int(rc or 0)
