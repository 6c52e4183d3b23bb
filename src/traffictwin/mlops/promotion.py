"""Promotion run: register the freshly trained models, decide every gate, then apply.

The workflow (``pipelines/promote.py``) builds one :class:`GateJob` per registered model from
params.yaml — its gate, its model folder, and a callable that loads the fixed test set and returns
the evaluator — and calls :func:`promote` with :class:`PromotionSettings`. Here:

1. every candidate's ``model_meta.json`` and the run record of its training stage (MLflow run
   id) are read first (:func:`read_candidate`), so a missing model stops the run before
   anything changes;
2. under the registry-wide lock (:func:`traffictwin.mlops.registry.gate_lock`, held until the
   last alias moved: a second gate waits, then decides against the champion this one left),
   each candidate is registered once (:func:`traffictwin.mlops.registry.ensure_version`) and
   decided against its champion (:func:`traffictwin.mlops.registry.decide`);
3. only when every decision is taken are they applied (unless ``dry_run``), so an evaluation
   failure moves no alias. A champion that cannot be evaluated stops the run
   (:class:`traffictwin.mlops.gate.ChampionEvaluationError`) with every champion kept. If a
   champion moved between its decision and the apply (someone changed the alias without the
   lock), that model is decided again against the new champion; if it moves again, the run stops
   (:class:`traffictwin.mlops.registry.ChampionChangedError`).

After a decision is applied, the challenger's registered version gets a model card as its
description (:func:`model_card`: data, test metrics with their intervals, the gate's figures,
limits); a job's :class:`ModelCard` says what the workflow knows beyond the candidate's
``model_meta.json`` and the decision.

No params.yaml, no paths of the project: jobs and settings carry everything.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from traffictwin.mlops import registry as reg
from traffictwin.mlops.gate import Decision, Evaluator, Gate, outcome, short_reason

log = logging.getLogger("traffictwin.promotion")


@dataclass
class Candidate:
    """A newly trained model to put through the gate: its registered name and MLflow run."""

    name: str
    run_id: str
    model_uri: str | None
    meta_path: Path
    meta: dict[str, Any] = field(default_factory=dict)
    record_path: Path | None = None


def _read_json_object(path: Path, what: str) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise reg.RegistryError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise reg.RegistryError(f"{path}: {what} must be a JSON object")
    return data


def read_candidate(name: str, model_dir: str | Path, record_path: str | Path) -> Candidate:
    """The candidate of ``<model_dir>/model_meta.json`` (the model's facts) and ``record_path``, the
    run record of the stage that trained it (keys ``run_id``, optional ``model_uri``, and
    ``model_sha256``, which must be the SHA-256 of ``<model_dir>/model.ckpt``). The MLflow run
    id lives in the run record, outside the DVC-tracked model folder, so identical reruns give
    identical model folders. Errors name the file and the missing key."""
    model_dir, record_path = Path(model_dir), Path(record_path)
    meta_path = model_dir / "model_meta.json"
    if not meta_path.exists():
        raise reg.RegistryError(f"{meta_path}: not found (train the model first: `dvc repro`)")
    meta = _read_json_object(meta_path, "model meta")
    if not record_path.exists():
        raise reg.RegistryError(
            f"{record_path}: not found (the run record of the stage that trained {model_dir}; "
            "train the model first: `dvc repro`)"
        )
    record = _read_json_object(record_path, "run record")
    run_id = record.get("run_id")
    if not run_id:
        raise reg.RegistryError(
            f"{record_path}: no MLflow run id (key 'run_id'); "
            "was the model trained with tracking enabled?"
        )
    expected = record.get("model_sha256")
    ckpt = model_dir / "model.ckpt"
    if expected and ckpt.exists():
        from traffictwin.io.shards import sha256_file

        got = sha256_file(ckpt)
        if got != expected:
            raise reg.RegistryError(
                f"{record_path}: run record of another model than {ckpt} (model_sha256 "
                f"{str(expected)[:12]}…, the file has {got[:12]}…); re-run its training stage "
                "(`dvc repro -f <stage>`) or restore the matching reports/timings"
            )
    uri = record.get("model_uri")
    return Candidate(
        name=name,
        run_id=str(run_id),
        model_uri=str(uri) if uri else None,
        meta_path=meta_path,
        meta=meta,
        record_path=record_path,
    )


@dataclass(frozen=True)
class ModelCard:
    """What a version's model card says beyond the candidate's meta and the gate decision.

    ``data``: the data it was trained and tested on (one line); ``metrics``: test metrics in the
    evaluation JSON layout (``<k>: value`` and ``<k>_ci: {lo, hi}``); ``metrics_source``: where
    they come from (e.g. the evaluation stage's metrics file); ``limits``: known limits, one
    sentence each.
    """

    data: str = ""
    metrics: Mapping[str, Any] = field(default_factory=dict)
    metrics_source: str = ""
    limits: Sequence[str] = ()


@dataclass
class GateJob:
    """One registered model to gate.

    ``make_evaluator(candidate) -> (evaluate, test_fingerprint)`` loads the test set lazily
    (after every candidate was found); ``record_path``: the run record of the stage that
    trained ``model_dir`` (its MLflow run id); ``tags`` go on a newly registered version;
    ``card(candidate)`` gives the :class:`ModelCard` facts for the version's description
    (``None``: a card from the meta and the decision only).
    """

    name: str
    gate: Gate
    model_dir: Path
    make_evaluator: Callable[[Candidate], tuple[Evaluator, str]]
    record_path: Path
    tags: Mapping[str, str] = field(default_factory=dict)
    card: Callable[[Candidate], ModelCard] | None = None


def _fmt(v: Any) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def model_card(cand: Candidate, decision: Decision, card: ModelCard | None = None) -> str:
    """The Markdown description of the registered version ``decision.challenger_version``:
    the model (problem, MLflow run, profile), its data (``card.data`` and the data manifest
    hash of its meta), its test metrics with 95 % intervals, the promotion gate's figures on
    the fixed test set, and its limits."""
    card = card or ModelCard()
    m = cand.meta
    data_hash = m.get("data_manifest_hash") or m.get("data_manifest") or "unknown"
    n_params = m.get("param_count") or m.get("n_parameters")
    lines = [
        f"# {decision.name} v{decision.challenger_version}",
        "",
        f"traffictwin model, MLflow run `{cand.run_id}`"
        + (f", profile `{m['profile']}`" if m.get("profile") else "")
        + (f", {n_params} parameters" if n_params else ""),
        "",
        "## Data",
        "",
        *([card.data, ""] if card.data else []),
        f"Data manifest hash (SHA-256 of the training data's manifest.json): `{data_hash}`",
        "",
    ]
    # the workflow's evaluation (with intervals), else the gate's own figures on its test set
    metrics = card.metrics or decision.challenger_metrics
    source = card.metrics_source if card.metrics else "the promotion gate's fixed test set"
    values = {
        k: v
        for k, v in metrics.items()
        if not k.endswith("_ci") and isinstance(v, (int, float)) and not isinstance(v, bool)
    }
    if values:
        lines += ["## Test metrics", ""]
        if source:
            lines += [f"From {source}; 95 % bootstrap intervals where computed.", ""]
        lines += ["| metric | value | 95 % CI |", "| --- | --- | --- |"]
        for k, v in values.items():
            ci = metrics.get(f"{k}_ci")
            ci_s = (
                f"[{_fmt(ci.get('lo'))}, {_fmt(ci.get('hi'))}]" if isinstance(ci, Mapping) else "—"
            )
            lines.append(f"| {k} | {_fmt(v)} | {ci_s} |")
        lines.append("")
    gate = f"{decision.metric} ({decision.mode}, margin {decision.margin:g})"
    champ = (
        f"; champion v{decision.champion_version}: {_fmt(decision.champion_value)}"
        if decision.champion_value is not None
        else ""
    )
    lines += [
        "## Promotion gate",
        "",
        f"Decision **{decision.action}** on {gate}: this version {_fmt(decision.challenger_value)}"
        f"{champ}. {decision.reason}",
        f"Test set fingerprint: `{decision.test_fingerprint or 'unknown'}`",
        "",
    ]
    if card.limits:
        lines += ["## Limits", "", *[f"- {x}" for x in card.limits], ""]
    return "\n".join(lines)


@dataclass(frozen=True)
class PromotionSettings:
    """How to run the gate: aliases, decision log, and the run's switches."""

    champion_alias: str = reg.CHAMPION
    challenger_alias: str = reg.CHALLENGER
    log_path: Path | None = None  # promotion log (JSON lines); None: no log
    dry_run: bool = False  # decide, change nothing
    force: bool = False  # re-evaluate challengers that were already decided
    uri: str | None = None  # tracking/registry URI (default: traffictwin.mlops.tracking)
    lock_path: Path | None = None  # registry lock (default: registry.default_lock_path(uri))
    lock_timeout_s: float | None = None  # wait at most this long for the lock (None: no limit)


def select(jobs: Sequence[GateJob], only: Iterable[str] | None) -> list[GateJob]:
    """The jobs named in ``only`` (all if empty); an unknown name is a :class:`RegistryError`."""
    if not only:
        return list(jobs)
    wanted = set(only)
    unknown = wanted - {j.name for j in jobs}
    if unknown:
        raise reg.RegistryError(
            f"--only: unknown model(s) {sorted(unknown)}; known: {[j.name for j in jobs]}"
        )
    return [j for j in jobs if j.name in wanted]


@dataclass
class _Pending:
    """A decided job: what is needed to decide it again (and to describe its version)."""

    job: GateJob
    version: Any  # the registered ModelVersion
    evaluate: Evaluator
    fingerprint: str
    decision: Decision | None = None
    candidate: Candidate | None = None


def _decide(cl, p: _Pending, settings: PromotionSettings) -> Decision:
    t0 = time.perf_counter()
    d = reg.decide(
        cl,
        p.job.name,
        p.version,
        p.evaluate,
        p.job.gate,
        test_fingerprint=p.fingerprint,
        champion_alias=settings.champion_alias,
        force=settings.force,
    )
    log.info(
        "%s v%s: %s — %s (%.1f s)",
        d.name,
        d.challenger_version,
        d.action,
        d.reason,
        time.perf_counter() - t0,
    )
    return d


def _decide_all(cl, jobs: Sequence[GateJob], settings: PromotionSettings) -> list[_Pending]:
    candidates = [read_candidate(j.name, j.model_dir, j.record_path) for j in jobs]
    pending = []
    for job, cand in zip(jobs, candidates, strict=True):
        if settings.dry_run:  # the version it would be: registered already, or planned
            mv = reg.planned_version(cl, job.name, cand.run_id, cand.model_uri, tags=job.tags)
        else:
            mv = reg.ensure_version(cl, job.name, cand.run_id, cand.model_uri, tags=job.tags)
        evaluate, fingerprint = job.make_evaluator(cand)
        p = _Pending(job, mv, evaluate, fingerprint, candidate=cand)
        p.decision = _decide(cl, p, settings)
        pending.append(p)
    return pending


def decide_all(cl, jobs: Sequence[GateJob], settings: PromotionSettings) -> list[Decision]:
    """Register every candidate (once) and decide it against its champion; changes no alias.

    Call it under :func:`traffictwin.mlops.registry.gate_lock` if the decisions will be applied.
    """
    return _decisions(_decide_all(cl, jobs, settings))


def _decisions(pending: Sequence[_Pending]) -> list[Decision]:
    return [p.decision for p in pending if p.decision is not None]


def _apply_pending(cl, pending: Sequence[_Pending], settings: PromotionSettings) -> None:
    for p in pending:
        try:
            _apply_one(cl, p.decision, settings)  # type: ignore[arg-type]
        except reg.ChampionChangedError as exc:
            log.warning("%s; deciding again", exc)
            p.decision = _decide(cl, p, settings)
            _apply_one(
                cl, p.decision, settings
            )  # a second move: ChampionChangedError stops the run
        _describe(cl, p)


def _describe(cl, p: _Pending) -> None:
    """The model card as the description of the decided version (an ``unchanged`` decision
    keeps the card written when it was decided)."""
    d = p.decision
    if d is None or p.candidate is None or d.action == "unchanged":
        return
    card = p.job.card(p.candidate) if p.job.card is not None else None
    cl.update_model_version(
        d.name, str(d.challenger_version), description=model_card(p.candidate, d, card)
    )


def _apply_one(cl, d: Decision, settings: PromotionSettings) -> None:
    reg.apply(
        cl,
        d,
        log_path=settings.log_path,
        champion_alias=settings.champion_alias,
        challenger_alias=settings.challenger_alias,
    )


def apply_all(cl, decisions: Sequence[Decision], settings: PromotionSettings) -> None:
    """Apply decisions (tags, log line, aliases) in order.

    A decision whose champion moved since it was taken raises
    :class:`traffictwin.mlops.registry.ChampionChangedError` (use :func:`promote`, which decides
    such a model again).
    """
    for d in decisions:
        _apply_one(cl, d, settings)


def lock_path(settings: PromotionSettings) -> Path:
    """The registry lock file of ``settings`` (its ``lock_path``, else next to the registry)."""
    return Path(settings.lock_path) if settings.lock_path else reg.default_lock_path(settings.uri)


def promote(
    jobs: Sequence[GateJob],
    settings: PromotionSettings,
    *,
    client=None,
    before_apply: Callable[[list[Decision]], None] | None = None,
) -> list[Decision]:
    """Decide every job, then apply the decisions unless ``settings.dry_run``; returns them.

    The promotion log is checked first (:func:`traffictwin.mlops.registry.check_log_path`). A dry
    run registers no version (a candidate not yet registered is evaluated from its logged model,
    :func:`traffictwin.mlops.registry.planned_version`), moves no alias, records no tag and
    writes no file (no lock file either: it changes nothing another gate could race with).

    Holds the registry lock (:func:`lock_path`) from the first decision to the last alias move.
    ``before_apply(decisions)`` is called between the two (e.g. a workflow's last chance to stop;
    an exception there applies nothing).
    """
    if settings.log_path is not None and not settings.dry_run:
        reg.check_log_path(settings.log_path, "promotion log")  # before anything changes
    if settings.dry_run and client is None:
        from traffictwin.mlops.stores import sqlite_path
        from traffictwin.mlops.tracking import tracking_uri

        db = sqlite_path(settings.uri or tracking_uri())
        if db is not None and not db.exists():
            raise reg.RegistryError(
                f"{db}: no MLflow database (a dry run creates none); run the pipeline first"
            )
    cl = client if client is not None else reg.client(settings.uri)
    if settings.dry_run:  # registers nothing, moves nothing, writes no file (not even the lock)
        pending = _decide_all(cl, jobs, settings)
        if before_apply is not None:
            before_apply(_decisions(pending))
        return _decisions(pending)
    with reg.gate_lock(lock_path(settings), timeout_s=settings.lock_timeout_s):
        pending = _decide_all(cl, jobs, settings)
        if before_apply is not None:
            before_apply(_decisions(pending))
        if not settings.dry_run:
            _apply_pending(cl, pending, settings)
    return _decisions(pending)


def format_decision(d: Decision) -> str:
    """One line per decision for a terminal: name, version, action and both figures (or why the
    champion was skipped)."""
    fig = ""
    if d.challenger_value is not None:
        fig = f"  challenger {d.challenger_value:.6g}"
        if d.champion_value is not None:
            fig += f"  champion v{d.champion_version} {d.champion_value:.6g}"
        elif d.champion_incompatible:
            fig += f"  champion v{d.champion_version} skipped: {d.champion_incompatible}"
    return f"{d.name:28s} v{d.challenger_version:>3s}  {d.action:9s}{fig}"


TABLE_COLUMNS = ("model", "version", "decision", "metric", "value", "champion", "why")


def _value(v: float | None) -> str:
    return "—" if v is None else f"{v:.6g}"


def table_rows(decisions: Sequence[Decision]) -> list[tuple[str, ...]]:
    """One row of :data:`TABLE_COLUMNS` per decision: model name, version, decision
    (:func:`traffictwin.mlops.gate.outcome`: ``champion`` / ``challenger`` / ``rejected``), the
    gate metric compared (and which way is better), this version's and the champion's figure on
    the gate set ("—" when not evaluated), and the short reason
    (:func:`traffictwin.mlops.gate.short_reason`)."""
    rows = []
    for d in decisions:
        better = "lower" if d.mode == "min" else "higher"
        champ = "—"
        if d.champion_value is not None:
            champ = f"{_value(d.champion_value)} (v{d.champion_version})"
        elif d.champion_version is not None and d.champion_incompatible:
            champ = f"skipped (v{d.champion_version})"
        rows.append(
            (
                d.name,
                f"v{d.challenger_version}",
                outcome(d),
                f"{d.metric} ({better} is better)",
                _value(d.challenger_value),
                champ,
                short_reason(d),
            )
        )
    return rows


def format_table(decisions: Sequence[Decision], *, dry_run: bool = False) -> str:
    """The decisions as a table for a terminal: a header (:data:`TABLE_COLUMNS`) and one row per
    model (:func:`table_rows`), columns padded to their widest cell; after a dry run a last line
    says that nothing was applied."""
    rows = [TABLE_COLUMNS, *table_rows(decisions)]
    widths = [max(len(r[i]) for r in rows) for i in range(len(TABLE_COLUMNS) - 1)]
    lines = [
        "  ".join([*(c.ljust(w) for c, w in zip(r[:-1], widths, strict=True)), r[-1]]).rstrip()
        for r in rows
    ]
    if not decisions:
        lines.append("(no model to gate)")
    if dry_run:
        lines.append(
            "dry run: nothing applied (nothing registered, no alias moved, no decision recorded; "
            "v(new): a candidate not yet registered)"
        )
    return "\n".join(lines)
