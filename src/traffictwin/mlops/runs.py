"""Compare MLflow runs of one experiment as a table (``traffictwin runs compare --experiment fusion``).

Every training stage logs the same parameter names (the flattened config) and metric names
(``split/name``) across runs, and every run carries the tags of
:func:`traffictwin.mlops.tracking.base_tags` (``git_commit``, ``profile``, ``dvc_exp_name``,
``pipeline_run`` …), so runs from different ``dvc repro`` / ``dvc exp run`` invocations line
up column by column. :func:`compare_runs` returns that table as a DataFrame; :func:`format_runs`
renders it as text for a terminal.
"""

from __future__ import annotations

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
) -> pd.DataFrame:
    """One row per run of ``experiment`` (newest first), columns::

        run_name, run_id, status, start_time (UTC), profile, dvc_stage, git_commit (8 chars),
        dvc_exp_name, pipeline_run, param:<name>..., <metric>...

    ``metrics``: metric names to show (default: every metric logged by any of the runs, sorted;
    a requested name no run has is an error). The value is the metric's last logged value.
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
    metric_cols = _metric_columns(runs, metrics, experiment)
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


def _metric_columns(runs: list, metrics: Sequence[str] | None, experiment: str) -> list[str]:
    """``metrics`` (each logged by some run, unless there are no runs), or every logged metric
    name, sorted."""
    all_metrics = sorted({k for r in runs for k in r.data.metrics})
    if metrics is None:
        return all_metrics
    missing = [m for m in metrics if m not in all_metrics]
    if missing and runs:
        raise RunsError(
            f"metric(s) {missing} not logged by any run of {experiment!r} (available: {all_metrics})"
        )
    return list(metrics)


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
    a data manifest hash) cut to 12 characters + ``…``.
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
        for c in out.columns:
            out[c] = out[c].map(lambda v: v[:12] + "…" if isinstance(v, str) and len(v) > 24 else v)
    return out.to_string(index=False)
