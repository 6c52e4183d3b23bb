"""Acceptance thresholds, in one place: what a target checks (:class:`Threshold`, built from the
``acceptance`` config group by :func:`thresholds`) and how a figure is judged against it
(:func:`judge`). Every problem's targets module (fusion, risk, stereo, twin) judges through
:func:`judge`; the stages read ``acceptance.<problem>`` and pass the thresholds in.

A threshold: ``metric`` (the figure it judges: a metrics-file key or a short metric id),
``operator`` (``<=``, ``<``, ``>=``, ``>``) and ``value``; ``judged_on``: the point estimate
(default), the whole ``interval`` (its far end: the lower end for ``>``/``>=``, the upper end for
``<``/``<=``), or one end (``lo``, ``hi``); ``also``: a second condition on the same figure
(e.g. the interval's lower end >= 0.05); ``configs``: the pose configurations it is judged at
(None: every one); ``description``: what it checks (may hold fields the targets module fills,
``{t}``, ``{trans_m:g}``); ``format``: how the report prints the figure.
"""

from __future__ import annotations

import math
import operator as _op
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from numbers import Real
from typing import Any

from traffictwin.config import ConfigError

__all__ = [
    "FAIL",
    "JUDGED_ON",
    "NOT_EVALUATED",
    "OPERATORS",
    "PASS",
    "Condition",
    "Judgement",
    "Threshold",
    "for_problem",
    "judge",
    "thresholds",
]

PASS, FAIL, NOT_EVALUATED = "pass", "fail", "not evaluated"
OPERATORS: dict[str, Callable[[float, float], bool]] = {
    "<=": _op.le,
    "<": _op.lt,
    ">=": _op.ge,
    ">": _op.gt,
}
#: what a condition compares: the point estimate, the whole interval (its far end), one end
JUDGED_ON = ("estimate", "interval", "lo", "hi")


def _num(x: Any) -> float | None:
    """``x`` as a finite float, else None (None, NaN, inf, not a number)."""
    if isinstance(x, bool) or not isinstance(x, Real):
        return None
    v = float(x)
    return v if math.isfinite(v) else None


@dataclass(frozen=True)
class Condition:
    """``<figure> <operator> <value>``; the figure is ``judged_on`` the estimate, the interval or
    one of its ends."""

    operator: str
    value: float
    judged_on: str = "estimate"

    def holds(self, x: Any) -> bool:
        """``x <operator> value``; False for a missing or non-finite ``x``."""
        v = _num(x)
        return v is not None and bool(OPERATORS[self.operator](v, self.value))

    def figure(self, estimate: Any, lo: Any, hi: Any) -> Any:
        """The number this condition compares (for ``interval``: the far end)."""
        if self.judged_on == "interval":
            return lo if self.operator in (">=", ">") else hi
        return {"estimate": estimate, "lo": lo, "hi": hi}[self.judged_on]

    @property
    def text(self) -> str:
        """``"<= 0.3"`` (with the end judged where it is not the estimate)."""
        on = {"estimate": "", "interval": "whole interval ", "lo": "lower end ", "hi": "upper end "}
        return f"{on[self.judged_on]}{self.operator} {self.value:g}"


@dataclass(frozen=True)
class Threshold(Condition):
    """One acceptance threshold (see the module docstring); ``name`` says what it checks."""

    name: str = ""
    metric: str = ""
    description: str = ""
    also: Condition | None = None
    configs: tuple[str, ...] | None = None
    format: str | None = None

    @property
    def text(self) -> str:
        """The whole condition, ``"<= 0.3"`` or ``">= 0.1 and lower end >= 0.05"``."""
        base = super().text
        return base if self.also is None else f"{base} and {self.also.text}"


@dataclass(frozen=True)
class Judgement:
    """A figure judged against a threshold: ``status`` (:data:`PASS` / :data:`FAIL` /
    :data:`NOT_EVALUATED`), ``met`` (None: not evaluated); ``ci_beyond``: the whole interval lies
    on the side of the main condition's verdict; ``ci_passes``: the whole interval meets the main
    condition (both False where nothing was judged)."""

    status: str
    met: bool | None
    ci_beyond: bool
    ci_passes: bool


def judge(t: Condition, estimate: Any, lo: Any = None, hi: Any = None) -> Judgement:
    """``estimate`` with its interval ``[lo, hi]`` against ``t`` (and ``t.also``). Not evaluated
    where the estimate (or the end ``t`` is judged on) is missing or not finite; a missing far end
    of the interval fails an ``interval`` condition."""
    if _num(estimate) is None or (
        t.judged_on in ("lo", "hi") and _num(t.figure(estimate, lo, hi)) is None
    ):
        return Judgement(NOT_EVALUATED, None, False, False)
    ok = t.holds(t.figure(estimate, lo, hi))
    far, near = (lo, hi) if t.operator in (">=", ">") else (hi, lo)
    passes = t.holds(far)
    beyond = passes if ok else (_num(near) is not None and not t.holds(near))
    also = getattr(t, "also", None)
    met = ok and (also is None or also.holds(also.figure(estimate, lo, hi)))
    return Judgement(PASS if met else FAIL, met, beyond, passes)


# --------------------------------------------------------------------------- configuration
def _condition(node: Any, key: str, source: str) -> tuple[str, float, str]:
    if not isinstance(node, Mapping):
        raise ConfigError(f"{source}: '{key}' must be a mapping, got {type(node).__name__}")
    for f in ("operator", "value"):
        if f not in node:
            raise ConfigError(f"{source}: key '{key}.{f}' is missing")
    op = node["operator"]
    if op not in OPERATORS:
        raise ConfigError(
            f"{source}: '{key}.operator' must be one of {list(OPERATORS)}, got {op!r}"
        )
    v = node["value"]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ConfigError(f"{source}: '{key}.value' must be a finite number, got {v!r}")
    on = node.get("judged_on", "estimate")
    if on not in JUDGED_ON:
        raise ConfigError(
            f"{source}: '{key}.judged_on' must be one of {list(JUDGED_ON)}, got {on!r}"
        )
    return op, float(v), on


_FIELDS = {"metric", "operator", "value", "judged_on", "also", "configs", "description", "format"}


def threshold(node: Any, name: str, key: str, source: str = "params.yaml") -> Threshold:
    """The threshold ``name`` from its config mapping ``node`` (at ``key``); a
    :class:`~traffictwin.config.ConfigError` names the key of a missing field, an unknown
    operator or a value that is not a finite number."""
    op, v, on = _condition(node, key, source)
    unknown = sorted(set(node) - _FIELDS)
    if unknown:
        raise ConfigError(
            f"{source}: '{key}': unknown field(s) {unknown} (allowed: {sorted(_FIELDS)})"
        )
    metric = node.get("metric")
    if not isinstance(metric, str) or not metric:
        raise ConfigError(f"{source}: '{key}.metric' must be a non-empty string, got {metric!r}")
    also = None
    if node.get("also") is not None:
        a = node["also"]
        extra = (
            sorted(set(a) - {"operator", "value", "judged_on"}) if isinstance(a, Mapping) else []
        )
        if extra:
            raise ConfigError(f"{source}: '{key}.also': unknown field(s) {extra}")
        also = Condition(*_condition(a, f"{key}.also", source))
    configs = node.get("configs")
    if configs is not None:
        if isinstance(configs, str) or not isinstance(configs, Iterable):
            raise ConfigError(
                f"{source}: '{key}.configs' must be a list of configuration names or null"
            )
        configs = tuple(str(c) for c in configs)
    desc, fmt = node.get("description", ""), node.get("format")
    if not isinstance(desc, str):
        raise ConfigError(f"{source}: '{key}.description' must be a string, got {desc!r}")
    if fmt is not None and not isinstance(fmt, str):
        raise ConfigError(f"{source}: '{key}.format' must be a string, got {fmt!r}")
    return Threshold(op, v, on, name, metric, desc, also, configs, fmt)


def thresholds(
    node: Any,
    key: str,
    names: Iterable[str] | None = None,
    source: str = "params.yaml",
) -> dict[str, Threshold]:
    """Every threshold of one problem's mapping ``node`` (``acceptance.<problem>`` at ``key``),
    in order. ``names``: the targets the problem's module judges — the config must hold exactly
    these (a missing or unknown name is a :class:`~traffictwin.config.ConfigError`)."""
    from omegaconf import OmegaConf

    if OmegaConf.is_config(node):
        node = OmegaConf.to_container(node, resolve=True)
    if not isinstance(node, Mapping) or not node:
        raise ConfigError(f"{source}: '{key}' must be a non-empty mapping of thresholds")
    out = {str(n): threshold(e, str(n), f"{key}.{n}", source) for n, e in node.items()}
    if names is not None:
        want = list(names)
        missing, unknown = [n for n in want if n not in out], [n for n in out if n not in want]
        if missing:
            raise ConfigError(f"{source}: '{key}': no threshold for {missing}")
        if unknown:
            raise ConfigError(f"{source}: '{key}': unknown target(s) {unknown} (known: {want})")
    return out


def for_problem(
    cfg: Any, problem: str, names: Iterable[str] | None = None, source: str = "params.yaml"
) -> dict[str, Threshold]:
    """``acceptance.<problem>`` of the loaded parameters ``cfg`` as thresholds (see
    :func:`thresholds`)."""
    key = f"acceptance.{problem}"
    node = cfg.get("acceptance") if isinstance(cfg, Mapping) or hasattr(cfg, "get") else None
    if node is None or problem not in node:
        raise ConfigError(f"{source}: key '{key}' is missing")
    return thresholds(node[problem], key, names, source)
