"""SGM variants around the configured matcher, and the rule that picks one on validation
(stage sgm_variants).

A variant changes some of :class:`~traffictwin.stereo.sgm.SgmParams`' settings (block size,
uniqueness ratio, speckle filter, grey or colour matching); the search range stays the configured
one. The rule is fixed before any variant is scored: among the variants that estimate at least as
large a share of the object pixels at the critical distances as the configured matcher (no buying
accuracy by dropping the pixels risk reads), the lowest median relative range error on those
pixels; ties go to the lower end-point error, then to the configured matcher.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, replace
from typing import Any

from traffictwin.stereo.sgm import SgmParams

#: the settings a variant may change (the search range is the configured one)
VARIANT_FIELDS = ("block_size", "uniqueness_ratio", "speckle_window", "gray")
#: the rule's criterion, its density guard and its tie-break (keys of the validation figures)
CRITERION = "crit_obj_relerr_median"
GUARD = "crit_obj_density"
TIE_BREAK = "epe"


def variant_name(p: SgmParams) -> str:
    """A short, unique name: ``bs5-ur10-sw100-colour``."""
    return (
        f"bs{p.block_size}-ur{p.uniqueness_ratio}-sw{p.speckle_window}-"
        f"{'grey' if p.gray else 'colour'}"
    )


def variant_grid(base: SgmParams, grid: Mapping[str, Sequence[Any]]) -> list[SgmParams]:
    """Every combination of ``grid``'s values (fields of :data:`VARIANT_FIELDS`) on top of
    ``base``, the configured matcher first and once. ValueError naming a field that is not a
    variant field, an empty list, or a combination the matcher refuses (e.g. an even block)."""
    bad = sorted(set(grid) - set(VARIANT_FIELDS))
    if bad:
        raise ValueError(f"sgm variants: unknown fields {bad}; expected some of {VARIANT_FIELDS}")
    for k, values in grid.items():
        if isinstance(values, (str, bytes)) or not isinstance(values, Sequence) or not values:
            raise ValueError(f"sgm variants: '{k}' must be a non-empty list, got {values!r}")
    keys = list(grid)
    out = [base]
    for combo in itertools.product(*(grid[k] for k in keys)):
        try:
            v = replace(base, **dict(zip(keys, combo)))
        except (TypeError, ValueError) as exc:
            raise ValueError(
                f"sgm variants: {dict(zip(keys, combo))} is not a matcher: {exc}"
            ) from None
        if v not in out:
            out.append(v)
    return out


def choose_variant(
    figures: Mapping[str, Mapping[str, float | None]], configured: str
) -> tuple[str, str]:
    """``(name, why)`` of the variant the rule (module docstring) picks from ``figures`` (name ->
    validation figures with :data:`CRITERION`, :data:`GUARD`, :data:`TIE_BREAK`; None = not
    measurable); the configured matcher when no variant qualifies."""

    def num(v: float | None) -> float:
        return float(v) if v is not None and math.isfinite(float(v)) else math.nan

    if configured not in figures:
        raise ValueError(f"sgm variants: the configured matcher '{configured}' was not scored")
    floor = num(figures[configured].get(GUARD))
    ok = [
        n
        for n, f in figures.items()
        if math.isfinite(num(f.get(CRITERION)))
        and (not math.isfinite(floor) or num(f.get(GUARD)) >= floor)
    ]
    if not ok:
        return configured, "no variant has a critical-object range error: the configured one"
    best = min(
        ok,
        key=lambda n: (
            num(figures[n].get(CRITERION)),
            num(figures[n].get(TIE_BREAK))
            if math.isfinite(num(figures[n].get(TIE_BREAK)))
            else math.inf,
            n != configured,
        ),
    )
    why = (
        f"lowest validation {CRITERION} among the {len(ok)} of {len(figures)} variants with "
        f"{GUARD} >= the configured matcher's"
    )
    return best, why


def settings(p: SgmParams) -> dict[str, Any]:
    """The matcher's settings as written in params.yaml (``risk_data.sgm``)."""
    return asdict(p)
