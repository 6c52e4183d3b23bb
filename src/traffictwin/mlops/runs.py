"""Compare MLflow runs of one experiment as a table (``traffictwin runs compare --experiment fusion``).

Every training stage logs the same parameter names (the flattened config) and metric names
(``split/name``) across runs, and every run carries the tags of
:func:`traffictwin.mlops.tracking.base_tags` (``git_commit``, ``profile``, ``dvc_exp_name``,
``pipeline_run`` …), so runs from different ``dvc repro`` / ``dvc exp run`` invocations line
up column by column. :func:`compare_runs` returns that table as a DataFrame; :func:`format_runs`
renders it as text for a terminal.
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Sequence
from typing import Any

import pandas as pd

from traffictwin.mlops import tracking
from traffictwin.mlops.uris import mask_uri

ID_COLUMNS = ("run_name", "run_id", "status", "start_time")
TAG_COLUMNS = ("profile", "dvc_stage", "git_commit", "dvc_exp_name", "pipeline_run")


class RunsError(LookupError):
    """The experiment does not exist in the tracking store (message names both)."""


def compare_runs(
    experiment: str,
    metrics: Sequence[str] | None = None,
    uri: str | None = None,
    *,
    params: Sequence[str] | None = None,
    filter_string: str = "",
    include_unfinished: bool = False,
    max_results: int = 5000,
    configuration: str | None = None,
) -> pd.DataFrame:
    """One row per run of ``experiment`` (newest first), columns::

        run_name, run_id, status, start_time (UTC), profile, dvc_stage, git_commit (8 chars),
        dvc_exp_name, pipeline_run, param:<name>..., <metric>...

    ``metrics``: metric names to show (default: every metric logged by any of the runs, sorted),
    read by :func:`resolve_metrics`: a logged name as is, a per-configuration name without its
    configuration (``test/kld_fou_mean`` for ``test/<cfg>/kld_fou_mean``) with ``configuration``
    (e.g. ``"D"``) or, without it, as one column per configuration; a name no run has is an error
    naming up to 5 close matches. The value is the metric's last logged value.
    ``params``: parameter names to show (default: those whose value differs between the runs,
    i.e. what the compared experiments changed). ``uri``: tracking URI (default
    :func:`traffictwin.mlops.tracking.tracking_uri`). ``filter_string``: an MLflow search filter,
    e.g. ``"tags.profile = 'ci'"``. Unfinished (running / failed) runs are left out unless
    ``include_unfinished``.
    """
    from mlflow.tracking import MlflowClient

    uri = uri or tracking.tracking_uri()
    client = MlflowClient(tracking_uri=uri)
    exp = client.get_experiment_by_name(experiment)
    if exp is None:
        names = sorted(e.name for e in client.search_experiments())
        raise RunsError(
            f"MLflow experiment {experiment!r} not found at {mask_uri(uri)} (experiments there: {names or 'none'})"
        )
    runs = _search_runs(client, exp.experiment_id, filter_string, max_results)
    if not include_unfinished:
        runs = [r for r in runs if r.info.status == "FINISHED"]
    metric_cols = _metric_columns(runs, metrics, experiment, configuration)
    if params is None:
        names = sorted({k for r in runs for k in r.data.params})
        param_cols = [k for k in names if len({r.data.params.get(k) for r in runs}) > 1]
    else:
        param_cols = list(params)
    rows = [_run_row(r, param_cols, metric_cols) for r in runs]
    columns = [*ID_COLUMNS, *TAG_COLUMNS, *(f"param:{p}" for p in param_cols), *metric_cols]
    return pd.DataFrame(rows, columns=columns)


def _search_runs(client: Any, experiment_id: str, filter_string: str, max_results: int) -> list:
    """Up to ``max_results`` runs of the experiment matching ``filter_string``, newest first
    (MLflow's pages of at most 1000 runs followed)."""
    runs: list[Any] = []
    token = None
    while len(runs) < max_results:
        page = client.search_runs(
            [experiment_id],
            filter_string=filter_string,
            max_results=min(1000, max_results - len(runs)),
            order_by=["attributes.start_time DESC"],
            page_token=token,
        )
        runs.extend(page)
        token = page.token
        if not token:
            break
    return runs


def _metric_columns(
    runs: list, metrics: Sequence[str] | None, experiment: str, configuration: str | None
) -> list[str]:
    """:func:`resolve_metrics` of ``metrics`` against every metric the runs logged (all of them,
    sorted, when ``metrics`` is None; ``metrics`` as given when there are no runs)."""
    all_metrics = sorted({k for r in runs for k in r.data.metrics})
    if metrics is None:
        return all_metrics
    if not runs:
        return list(metrics)
    return resolve_metrics(metrics, all_metrics, configuration=configuration, experiment=experiment)


#: the longest error message :func:`resolve_metrics` raises (characters; one line)
MAX_ERROR_CHARS = 300


def resolve_metrics(
    requested: Sequence[str],
    available: Sequence[str],
    *,
    configuration: str | None = None,
    experiment: str = "",
) -> list[str]:
    """The logged metric names for the names a user typed, in order.

    A name in ``available`` stays as it is. Otherwise ``split/name`` is read as the
    per-configuration ``split/<configuration>/name`` (the evaluation logs ``test/D/kld_fou_mean``):
    with ``configuration`` that one name, without it one name per configuration that has it
    (sorted). A name that matches nothing raises :class:`RunsError`: one line of at most
    :data:`MAX_ERROR_CHARS` characters naming up to 5 close matches (:mod:`difflib`).
    """
    have = set(available)
    out: list[str] = []
    for name in requested:
        if name in have:
            out.append(name)
            continue
        split, _, rest = name.partition("/")
        if rest:
            if configuration is not None:
                found = (
                    [f"{split}/{configuration}/{rest}"]
                    if f"{split}/{configuration}/{rest}" in have
                    else []
                )
            else:
                found = sorted(
                    a
                    for a in available
                    if a.count("/") == name.count("/") + 1
                    and a.startswith(f"{split}/")
                    and a.endswith(f"/{rest}")
                )
            if found:
                out.extend(found)
                continue
        raise RunsError(_unknown_metric(name, available, configuration, experiment))
    return out


def _unknown_metric(
    name: str, available: Sequence[str], configuration: str | None, experiment: str
) -> str:
    """One line (at most :data:`MAX_ERROR_CHARS` characters): the unknown ``name`` and up to 5
    close matches among ``available`` (also matched with ``configuration`` put in)."""
    split, _, rest = name.partition("/")
    probes = [name] + ([f"{split}/{configuration}/{rest}"] if configuration and rest else [])
    close: list[str] = []
    for probe in probes:
        for m in difflib.get_close_matches(probe, available, n=5, cutoff=0.6):
            if m not in close:
                close.append(m)
    where = f" of {experiment!r}" if experiment else ""
    cfg = f" (configuration {configuration!r})" if configuration else ""
    head = f"metric {name!r}{cfg} not logged by any run{where}"
    tail = f"; {len(available)} names in all (omit --metrics to list them)"
    shown: list[str] = []
    for m in close[:5]:
        candidate = f"{head}; close matches: {', '.join([*shown, m])}{tail}"
        if len(candidate) > MAX_ERROR_CHARS:
            break
        shown.append(m)
    if shown:
        return f"{head}; close matches: {', '.join(shown)}{tail}"
    return f"{head}; no close match{tail}"[:MAX_ERROR_CHARS]


def _run_row(r: Any, param_cols: list[str], metric_cols: list[str]) -> dict[str, Any]:
    """One run's row: ids, start time (UTC), tags (commit shortened to 8 characters), the
    parameters and the metrics' last values (NaN where the run has none)."""
    row: dict[str, Any] = {
        "run_name": r.info.run_name,
        "run_id": r.info.run_id,
        "status": r.info.status,
        "start_time": pd.Timestamp(r.info.start_time, unit="ms", tz="UTC")
        if r.info.start_time
        else pd.NaT,
    }
    for t in TAG_COLUMNS:
        v = r.data.tags.get(t, "")
        row[t] = v[:8] if t == "git_commit" else v
    for p in param_cols:
        row[f"param:{p}"] = r.data.params.get(p)
    for m in metric_cols:
        row[m] = r.data.metrics.get(m, math.nan)
    return row


def format_runs(df: pd.DataFrame, *, digits: int = 4, wide: bool = False) -> str:
    """Text table of :func:`compare_runs` output for a terminal.

    Floats with ``digits`` significant digits (missing metric: ``-``). Unless ``wide``: the run id
    shortened to 8 characters, empty tag columns dropped, text longer than 24 characters (e.g.
    a data manifest hash) cut to 12 characters + ``…``, except the run's name: it says what the
    experiment changed (``fusion-network [lr-low: fusion_model.optim.lr=0.002]``).
    """
    if df.empty:
        return "(no finished runs)"
    out = df.copy()
    if not wide:
        out["run_id"] = out["run_id"].str[:8]
        empty = [c for c in TAG_COLUMNS if c in out and (out[c].fillna("") == "").all()]
        out = out.drop(columns=empty)
    if "start_time" in out:
        out["start_time"] = out["start_time"].map(
            lambda t: "" if pd.isna(t) else t.strftime("%Y-%m-%d %H:%M")
        )
    for c in out.columns:
        if pd.api.types.is_float_dtype(out[c]):
            out[c] = out[c].map(
                lambda v: (
                    "-"
                    if v is None or (isinstance(v, float) and math.isnan(v))
                    else f"{v:.{digits}g}"
                )
            )
    out = out.fillna("-")
    if not wide:
        for c in out.columns.drop("run_name", errors="ignore"):
            out[c] = out[c].map(lambda v: v[:12] + "…" if isinstance(v, str) and len(v) > 24 else v)
    return out.to_string(index=False)
