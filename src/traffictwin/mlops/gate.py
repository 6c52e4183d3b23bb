"""The champion/challenger promotion decision, apart from any registry (no MLflow here).

:class:`Gate` compares two figures of one metric (``min`` or ``max`` is better) with an
absolute ``margin``; :func:`decide` evaluates a challenger and the current champion with one
``evaluate(model_uri)`` callable and returns a :class:`Decision`. The caller supplies what the
registry knows (versions, the challenger's previous ``gate.*`` tags, URIs);
:mod:`traffictwin.mlops.registry` is the MLflow adapter that looks those up and applies the
decision. Both figures are measured by the same callable on the same test set; the test-set
fingerprint is recorded with the decision.

Rules:

- no champion yet: the challenger becomes champion (``first``) if its figure is finite;
- the challenger is already the champion, or was already decided against the same champion
  on the same test set (its ``gate.*`` tags say so): ``unchanged`` (unless ``force``);
- a champion that cannot be evaluated stops the gate: :class:`ChampionEvaluationError` (the
  champion is kept). A load or evaluation error may be transient (a file briefly missing, a full
  disk), and replacing the champion on it once promoted a model 2000x worse;
- except a champion that is *known* incompatible: the evaluator raises
  :class:`IncompatibleModelError` (its recorded grid/architecture does not fit the current test
  set, or it was logged in a format that is never loaded). The reason is kept in the decision
  (``champion_incompatible``; the registry records it on the version) and the challenger is
  judged alone, as if there were no champion (``promoted`` if its figure is finite);
- otherwise the challenger is ``promoted`` only if it is better by more than ``margin``.

For people, :func:`outcome` says where a decision leaves the version (``champion``,
``challenger`` or ``rejected``) and :func:`short_reason` why, in a few words.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from typing import Any, Literal

from traffictwin.mlops.errors import GateError, IncompatibleModelError

__all__ = ["GateError", "IncompatibleModelError"]  # defined in errors.py, part of this API

Action = Literal["first", "promoted", "rejected", "unchanged"]
Outcome = Literal["champion", "challenger", "rejected"]
Evaluator = Callable[[str], Mapping[str, float]]


class ChampionEvaluationError(GateError):
    """The current champion could not be evaluated: the gate stops and the champion is kept."""


@dataclass(frozen=True)
class Gate:
    """Quality gate on one metric.

    ``metric``: key in the evaluation result (e.g. ``test/kld``); ``mode``: ``min`` (lower is
    better) or ``max``; ``margin``: absolute improvement (in the metric's units) the
    challenger must exceed to replace the champion (``>= 0``).
    """

    metric: str
    mode: Literal["min", "max"] = "min"
    margin: float = 0.0

    def __post_init__(self) -> None:
        if self.mode not in ("min", "max"):
            raise ValueError(f"gate mode must be 'min' or 'max', got {self.mode!r}")
        if not (
            isinstance(self.margin, (int, float))
            and math.isfinite(self.margin)
            and self.margin >= 0
        ):
            raise ValueError(f"gate margin must be a finite number >= 0, got {self.margin!r}")
        if not self.metric:
            raise ValueError("gate metric must be a non-empty metric name")

    def improvement(self, challenger: float, champion: float) -> float:
        """How much better the challenger is (positive = better), in metric units."""
        return (champion - challenger) if self.mode == "min" else (challenger - champion)

    def passes(self, challenger: float, champion: float | None) -> bool:
        """True if ``challenger`` should replace ``champion`` (``None``: no champion yet).

        A non-finite challenger figure never passes; a non-finite champion figure is beaten
        by any finite challenger.
        """
        if not math.isfinite(challenger):
            return False
        if champion is None or not math.isfinite(champion):
            return True
        return self.improvement(challenger, champion) > self.margin


@dataclass
class Decision:
    """One gate decision (JSON-serialisable via :meth:`to_dict`)."""

    name: str
    challenger_version: str
    challenger_run_id: str
    champion_version: str | None
    metric: str
    mode: str
    margin: float
    challenger_value: float | None
    champion_value: float | None
    action: Action
    reason: str
    test_fingerprint: str = ""
    challenger_metrics: dict[str, float] = field(default_factory=dict)
    champion_metrics: dict[str, float] = field(default_factory=dict)
    champion_incompatible: str = ""  # why the champion was skipped (known-incompatible), else ""
    timestamp: float = field(default_factory=time.time)
    earlier: str = ""  # unchanged as already decided: that earlier decision's action, else ""

    @property
    def promotes(self) -> bool:
        return self.action in ("first", "promoted")

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        if not d["earlier"]:
            del d["earlier"]  # the log's records (never unchanged) keep their keys
        d["event"] = "promotion"
        d["time"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(self.timestamp))
        return d


@dataclass(frozen=True)
class Version:
    """What the gate needs to know of one registered model version."""

    version: str
    uri: str
    run_id: str = ""
    tags: Mapping[str, str] = field(default_factory=dict)


def metric_value(result: Mapping[str, float], metric: str, who: str) -> float:
    """``result[metric]`` as a float; :class:`GateError` naming ``who`` if it is missing."""
    if metric not in result:
        raise GateError(f"evaluation of {who} returned no metric '{metric}' (got {sorted(result)})")
    return float(result[metric])


def already_decided(challenger: Version, champion: Version | None, test_fingerprint: str) -> bool:
    """True if the challenger's ``gate.*`` tags record a decision against this champion and test set."""
    tags = challenger.tags
    return (
        "gate.decision" in tags
        and champion is not None
        and tags.get("gate.champion_version") == champion.version
        and tags.get("gate.test_fingerprint", "") == test_fingerprint
    )


def compare(gate: Gate, challenger_value: float, champion_value: float) -> tuple[bool, str]:
    """Whether the challenger figure beats the champion figure, and the sentence that says why."""
    better = gate.passes(challenger_value, champion_value)
    word = "lower" if gate.mode == "min" else "higher"
    finite = math.isfinite(challenger_value) and math.isfinite(champion_value)
    if not finite:
        missing = [
            who
            for who, v in (("challenger", challenger_value), ("champion", champion_value))
            if not math.isfinite(v)
        ]
        return better, (
            f"{gate.metric}: challenger {challenger_value:.6g} vs champion {champion_value:.6g} "
            f"(no finite figure for the {' and the '.join(missing)}: nothing to compare, so "
            f"{'it passes' if better else 'it does not pass'} the margin {gate.margin:g})"
        )
    imp = gate.improvement(challenger_value, champion_value)
    return better, (
        f"{gate.metric}: challenger {challenger_value:.6g} vs champion {champion_value:.6g} "
        f"({word} is better; improvement {imp:.3g} {'>' if better else '<='} margin {gate.margin:g})"
    )


def _unchanged(
    common: dict[str, Any],
    challenger: Version,
    champion: Version | None,
    test_fingerprint: str,
    force: bool,
) -> Decision | None:
    """The ``unchanged`` decision when there is nothing to decide (the challenger is the
    champion, or was decided against it on this test set and not ``force``), else None."""
    unchanged = dict(challenger_value=None, champion_value=None, action="unchanged")
    if champion is not None and champion.version == challenger.version:
        return Decision(
            **common,
            **unchanged,
            champion_version=champion.version,
            reason="challenger is already the champion",
        )
    if not force and already_decided(challenger, champion, test_fingerprint):
        return Decision(
            **common,
            **unchanged,
            champion_version=champion.version,  # type: ignore[union-attr]
            reason=f"already decided against champion v{champion.version} on this test set "  # type: ignore[union-attr]
            f"({challenger.tags['gate.decision']})",
            earlier=str(challenger.tags["gate.decision"]),
        )
    return None


def _judged_alone(
    common: dict[str, Any],
    gate: Gate,
    champion: Version | None,
    ch_val: float,
    ch_metrics: dict[str, float],
    incompatible: str = "",
) -> Decision:
    """The challenger judged on its own figure (finite or not): there is no champion yet
    (``first``), or the champion is known-incompatible for the reason ``incompatible``."""
    ok = math.isfinite(ch_val)
    if champion is None:
        return Decision(
            **common,
            champion_version=None,
            challenger_value=ch_val,
            champion_value=None,
            action="first" if ok else "rejected",
            reason="no champion yet: first model becomes champion"
            if ok
            else f"{gate.metric} is not finite",
            challenger_metrics=ch_metrics,
        )
    return Decision(
        **common,
        champion_version=champion.version,
        challenger_value=ch_val,
        champion_value=None,
        action="promoted" if ok else "rejected",
        reason=f"champion v{champion.version} skipped, known-incompatible ({incompatible}); "
        + (
            f"challenger judged alone: {gate.metric} {ch_val:.6g} is finite"
            if ok
            else f"challenger {gate.metric} is not finite"
        ),
        challenger_metrics=ch_metrics,
        champion_incompatible=incompatible,
    )


def _champion_figures(
    name: str, champion: Version, evaluate: Evaluator, gate: Gate
) -> tuple[dict[str, float], float]:
    """The champion's metrics and its figure for ``gate.metric``. :class:`IncompatibleModelError`
    passes through; any other failure may be transient: :class:`ChampionEvaluationError`."""
    try:
        cp_metrics = {k: float(v) for k, v in evaluate(champion.uri).items()}
        cp_val = metric_value(cp_metrics, gate.metric, f"{name} v{champion.version} (champion)")
    except IncompatibleModelError:
        raise
    except Exception as exc:  # noqa: BLE001 - any other failure may be transient: stop, keep the champion
        raise ChampionEvaluationError(
            f"{name}: champion v{champion.version} could not be evaluated "
            f"({type(exc).__name__}: {one_line(exc)}); gate stopped, champion kept"
        ) from exc
    return cp_metrics, cp_val


def decide(
    name: str,
    challenger: Version,
    champion: Version | None,
    evaluate: Evaluator,
    gate: Gate,
    *,
    test_fingerprint: str = "",
    force: bool = False,
) -> Decision:
    """Evaluate ``challenger`` (and ``champion``, if any) with ``evaluate``; decide (see the module doc).

    ``evaluate(uri) -> {metric: value}`` scores one model on the fixed held-out test set; it is
    called with each version's ``uri``. Raises :class:`GateError` if the challenger's evaluation
    has no figure for ``gate.metric``.
    """
    common = dict(
        name=name,
        challenger_version=challenger.version,
        challenger_run_id=challenger.run_id or "",
        metric=gate.metric,
        mode=gate.mode,
        margin=float(gate.margin),
        test_fingerprint=test_fingerprint,
    )
    same = _unchanged(common, challenger, champion, test_fingerprint, force)
    if same is not None:
        return same
    ch_metrics = {k: float(v) for k, v in evaluate(challenger.uri).items()}
    ch_val = metric_value(ch_metrics, gate.metric, f"{name} v{challenger.version}")
    if champion is None:
        return _judged_alone(common, gate, None, ch_val, ch_metrics)
    try:
        cp_metrics, cp_val = _champion_figures(name, champion, evaluate, gate)
    except IncompatibleModelError as exc:
        return _judged_alone(common, gate, champion, ch_val, ch_metrics, one_line(exc))
    better, why = compare(gate, ch_val, cp_val)
    return Decision(
        **common,
        champion_version=champion.version,
        challenger_value=ch_val,
        champion_value=cp_val,
        action="promoted" if better else "rejected",
        reason=why,
        challenger_metrics=ch_metrics,
        champion_metrics=cp_metrics,
    )


def one_line(exc: BaseException, limit: int = 600) -> str:
    """``str(exc)`` on one line (newlines folded), at most ``limit`` characters."""
    text = " ".join(str(exc).split())
    return text if len(text) <= limit else text[: limit - 1] + "…"


def outcome(d: Decision) -> Outcome:
    """Where ``d`` leaves its version: ``champion`` (it became the champion, or already was),
    ``rejected`` (the champion stays: the version was not better by more than the margin, or its
    figure is not finite; also when an earlier run decided so against the same champion on the
    same test set), ``challenger`` (not judged now and not the champion: an earlier decision no
    longer describes the registry, e.g. after a rollback)."""
    if d.promotes:
        return "champion"
    if d.action == "rejected":
        return "rejected"
    if d.champion_version is not None and d.champion_version == d.challenger_version:
        return "champion"
    return "rejected" if d.earlier == "rejected" else "challenger"


def short_reason(d: Decision, limit: int = 60) -> str:
    """Why, in a few words (the full sentence is ``d.reason``): the gate metric's difference to
    the champion and the margin, "no champion yet", or why nothing was compared."""
    champ = f"champion v{d.champion_version}"
    if d.action == "unchanged":
        if d.champion_version == d.challenger_version:
            return "already the champion"
        return f"decided before against {champ}" + (f" ({d.earlier})" if d.earlier else "")
    ch = d.challenger_value
    if ch is None or not math.isfinite(ch):
        return f"{d.metric} is not finite"
    if d.champion_incompatible:
        why = d.champion_incompatible
        why = why if len(why) <= limit else why[: limit - 1] + "…"
        return f"{champ} skipped, incompatible: {why}"
    if d.champion_version is None or d.champion_value is None:
        return "no champion yet"
    cp = d.champion_value
    if not math.isfinite(cp):
        return f"{champ}'s {d.metric} is not finite"
    imp = (cp - ch) if d.mode == "min" else (ch - cp)
    margin = f"margin {d.margin:g}"
    if d.promotes:
        return f"{imp:.3g} better than {champ} ({margin})"
    if imp > 0:
        return f"only {imp:.3g} better than {champ} ({margin})"
    if imp == 0:
        return f"same as {champ}"
    return f"{-imp:.3g} worse than {champ}"
