"""The stereo section's tables of the learned stereo network and the SGM variants.

``stereo.json`` (stage stereo_learned: ``<sgm|learned>/<common|own>/<metric>[_lo|_hi]``,
``diff_learned_minus_sgm/<mask>/<metric>[_lo|_hi]``, ``generalisation``; its ``targets`` are
judged in the report's acceptance table) and ``sgm_variants.json`` (stage sgm_variants:
``validation.variants``, ``choice``, ``test``). A missing file or key is an ``n/a`` cell.
"""

from __future__ import annotations

from traffictwin.report import model as page
from traffictwin.report.model import Cell, Table, json_number
from traffictwin.stereo.report_tables import RANGE_ROWS, Row, compare_table, prose, value_ci

STEREO_FILE = "stereo.json"
VARIANTS_FILE = "sgm_variants.json"
MASK_LABELS = {
    "common": "pixels both sources estimate",
    "own": "each source's own estimated pixels",
}
#: the rows of the learned-stereo comparison: (label, metric key, format)
STEREO_ROWS: tuple[Row, ...] = (
    ("end-point error [px]", "epe", "f3"),
    ("bad-1 (> 1 px)", "bad1", "pct"),
    ("bad-2 (> 2 px)", "bad2", "pct"),
    ("density (share of GT pixels with an estimate)", "density", "pct"),
    *RANGE_ROWS,
    ("objects at the critical distances: median range error", "crit_obj_relerr_median", "pct"),
    ("objects at the critical distances: 90th percentile", "crit_obj_relerr_p90", "pct"),
    ("objects at the critical distances: share estimated", "crit_obj_density", "pct"),
)
#: the rows of the generalisation and chosen-variant tables, on each source's own pixels
GENERALISATION_ROWS = tuple(STEREO_ROWS[i] for i in (0, 1, 8, 9))
GENERALISATION_SOURCES = {"sgm": "SGM", "learned": "full network", "holdout": "without them"}
#: the paired differences shown: (label, metric key, format)
DIFF_ROWS: tuple[Row, ...] = (
    ("end-point error [px]", "epe", "f3"),
    ("critical objects: median range error", "crit_obj_relerr_median", "pct"),
)
#: the SGM variants table's columns: (header, figure key, format)
VARIANT_COLUMNS: tuple[Row, ...] = (
    ("EPE [px]", "epe", "f3"),
    ("bad-1", "bad1", "pct"),
    ("density", "density", "pct"),
    ("critical objects: median range error", "crit_obj_relerr_median", "pct"),
    ("critical objects: p90", "crit_obj_relerr_p90", "pct"),
    ("critical objects: share estimated", "crit_obj_density", "pct"),
)
#: how many variants the table lists beyond the configured and the chosen one
VARIANTS_SHOWN = 6


def learned_tables(src: page.Sources) -> list[Table]:
    """SGM vs the learned stereo network on the test split (both masks), their paired
    differences and the generalisation to unseen road templates."""
    if not src.has(STEREO_FILE):
        return []
    out = [
        compare_table(
            src,
            STEREO_FILE,
            f"{{source}}/{mask}/{{key}}",
            {"sgm": "SGM", "learned": "learned"},
            # the common mask's density is the same for both by construction
            [r for r in STEREO_ROWS if not (mask == "common" and r[1] == "density")],
            title=f"Learned stereo network vs SGM, fault-free test frames, {what} "
            "(reports/metrics/stereo.json)",
            anchor=f"stereo-learned-{mask}",
            note=prose("learned"),
        )
        for mask, what in MASK_LABELS.items()
    ]
    d = Table(
        "Learned stereo network − SGM, paired on the same test frames (reports/metrics/stereo.json)",
        ["pixels", "quantity", "difference", "95 % CI"],
        anchor="stereo-learned-difference",
        note=prose("learned_difference"),
    )
    for mask, what in MASK_LABELS.items():
        for label, key, fmt in DIFF_ROWS:
            cells = value_ci(src, STEREO_FILE, f"diff_learned_minus_sgm/{mask}/{key}", fmt)
            d.rows.append([Cell(what), Cell(label), *cells])
    return [*out, d, *generalisation_tables(src)]


def variant_tables(src: page.Sources) -> list[Table]:
    """SGM variants on validation (the configured matcher, the chosen one and the best others by
    the rule's criterion) and the chosen one against the configured matcher on test
    (``sgm_variants.json``)."""
    figs = src.get(VARIANTS_FILE, "validation.variants")
    if not isinstance(figs, dict) or not figs:
        return []
    chosen = str(src.get(VARIANTS_FILE, "choice.chosen"))
    configured = str(src.get(VARIANTS_FILE, "choice.configured"))
    guard = json_number(figs.get(configured, {}).get("crit_obj_density"))

    def crit(name: str) -> float:
        v = json_number(figs[name].get("crit_obj_relerr_median"))
        return float("inf") if v is None else v

    def role(n: str) -> str:
        if n == chosen == configured:
            return "configured and chosen"
        if n in (chosen, configured):
            return "chosen" if n == chosen else "configured"
        density = json_number(figs[n].get("crit_obj_density"))
        below = guard is not None and density is not None and density < guard
        return "below the density guard" if below else ""

    others = sorted((n for n in figs if n not in (chosen, configured)), key=crit)
    names = [configured] + ([chosen] if chosen != configured else []) + others[:VARIANTS_SHOWN]
    why = src.get(VARIANTS_FILE, "test.why")
    t = Table(
        f"SGM variants on {src.get(VARIANTS_FILE, 'validation.frames')} fault-free validation "
        f"frames, each variant's own estimated pixels ({len(figs)} scored; "
        "reports/metrics/sgm_variants.json)",
        ["variant", "role"] + [h for h, _, _ in VARIANT_COLUMNS],
        anchor="stereo-sgm-variants",
        note=prose("variants", rule=src.get(VARIANTS_FILE, "choice.rule"), why=why),
    )
    for n in names:
        key = f"validation.variants.{n}"
        cells = [src.cell(VARIANTS_FILE, f"{key}.{k}", fmt) for _, k, fmt in VARIANT_COLUMNS]
        t.rows.append([Cell(n), Cell(role(n)), *cells])
    if why:
        return [t]
    frames, seqs = (src.get(VARIANTS_FILE, f"test.test/{k}") for k in ("frames", "sequences"))
    c = compare_table(
        src,
        VARIANTS_FILE,
        "test.{source}/own/{key}",
        {"configured": "configured", "chosen": "chosen"},
        GENERALISATION_ROWS,
        title=f"SGM: the chosen variant ({chosen}) vs the configured matcher ({configured}) on the "
        "fault-free test frames, each one's own estimated pixels (reports/metrics/sgm_variants.json)",
        anchor="stereo-sgm-chosen",
        note=prose("chosen", frames=frames, sequences=seqs),
    )
    for label, key, fmt in DIFF_ROWS:  # the paired differences, on the pixels both estimate
        cells = value_ci(src, VARIANTS_FILE, f"test.diff_chosen_minus_configured/common/{key}", fmt)
        c.rows.append([Cell(f"{label} (chosen − configured)"), Cell(""), Cell(""), *cells])
    return [t, c]


def generalisation_tables(src: page.Sources) -> list[Table]:
    """The network trained without some road templates beside the full one and SGM on those
    templates' test frames (``stereo.json`` ``generalisation``), with the paired differences."""
    g = src.get(STEREO_FILE, "generalisation")
    if not isinstance(g, dict):
        return []
    names = ", ".join(str(t) for t in g.get("templates") or [])
    title = (
        f"Learned stereo on unseen road templates ({names}): fault-free test frames of those "
        "templates, each source's own estimated pixels (reports/metrics/stereo.json)"
    )
    if g.get("why"):
        t = Table(title, ["quantity", "value"], anchor="stereo-generalisation")
        t.rows.append([Cell("not measured"), Cell(str(g["why"]))])
        return [t]
    frames, seqs = g.get("test/frames"), g.get("test/sequences")
    t = compare_table(
        src,
        STEREO_FILE,
        "generalisation.{source}/own/{key}",
        GENERALISATION_SOURCES,
        GENERALISATION_ROWS,
        title=title,
        anchor="stereo-generalisation",
        note=prose("generalisation", frames=frames, sequences=seqs),
    )
    d = Table(
        f"Learned stereo without the templates {names} − with them, and − SGM, paired on the "
        "same frames (reports/metrics/stereo.json)",
        ["difference", "pixels", "quantity", "value", "95 % CI"],
        anchor="stereo-generalisation-difference",
        note=prose("generalisation_difference"),
    )
    for other, what in (("learned", "without − full network"), ("sgm", "without − SGM")):
        for mask, pixels in MASK_LABELS.items():
            for label, key, fmt in DIFF_ROWS:
                k = f"generalisation.diff_holdout_minus_{other}/{mask}/{key}"
                d.rows.append(
                    [Cell(what), Cell(pixels), Cell(label), *value_ci(src, STEREO_FILE, k, fmt)]
                )
    return [t, d]
