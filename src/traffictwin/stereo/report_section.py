"""The stereo part of the report: SGM depth accuracy by range, stereo-pair fault detection per
rule, and the camera-resolution study.

Reads ``disparity.json`` (stage disparity: ``<group>/<bin>_relerr_median|_p90|_valid_share|_gt_pixels``
with bins like ``z0-10m``, and ``<group>/bad2|d1|density|epe``), ``orb.json`` (stage orb_filter:
``rule_<rule>/<fault>_detection[_lo|_hi|_n]``, ``rule_<rule>/false_alarm[...]``,
``rule_<rule>/delay_detection_v<lo>-<hi>[...]``, ``rule_<rule>/configured``,
``sweep/min_valid_share_<t>_*``) and ``stereo_resolution.json`` (benchmarks/stereo_resolution.py:
``w<width>/<metric>``, ``diff_w<a>_minus_w<b>/<metric>[_lo|_hi]``) and ``stereo.json`` (stage
stereo_learned: ``<sgm|learned>/<common|own>/<metric>[_lo|_hi]``,
``diff_learned_minus_sgm/<mask>/<metric>[_lo|_hi]``, ``targets``). A missing file or key is an
``n/a`` cell, never an error. Entry point: :func:`provider`.
"""

from __future__ import annotations

import re

from traffictwin.report import model as page
from traffictwin.report.model import NA, NEVER, Cell, Table, fmt_value, json_number

DISPARITY_FILE = "disparity.json"
ORB_FILE = "orb.json"
RESOLUTION_FILE = "stereo_resolution.json"
STEREO_FILE = "stereo.json"
TITLE = "Stereo — SGM and the learned stereo network's range accuracy, stereo-pair fault detection"

FIGURES: dict[str, str] = {
    "stereo_learned_example": (
        "Test frames: left image | exact disparity | SGM | learned stereo network | the learned "
        "network's absolute error (px; black = no estimate)"
    ),
    "stereo_resolution": (
        "Relative depth error of SGM vs distance at two camera widths, with the critical "
        "distance band; SGM time per frame (benchmarks/stereo_resolution.py)"
    ),
}
#: rule key in orb.json -> row label
RULE_LABELS = {
    "orb_paper": "ORB, paper's rule over all cross-checked matches",
    "orb": "ORB, robust rule over reliable matches",
    "valid_share": "SGM valid share below threshold",
    "orb_or_valid_share": "robust ORB OR valid share",
}
GROUP_LABELS = {"all": "all pairs", "fault_none": "fault-free pairs", "test": "test split"}
CI_NOTE = (
    "Intervals: 95 % bootstrap over scenarios (driving sequences), since frames of one sequence "
    "are correlated (traffictwin.stats)."
)


def ci_cell(src: page.Sources, file: str, key: str, fmt: str = "pct") -> Cell:
    """``[lo, hi]`` of ``<key>_lo`` / ``<key>_hi`` in ``file``: a derived cell (n/a if absent)."""
    lo, hi = json_number(src.get(file, f"{key}_lo")), json_number(src.get(file, f"{key}_hi"))
    if lo is None or hi is None:
        return Cell(NA, title=f"no interval in reports/metrics/{file}: {key}_lo/_hi")
    return Cell(
        f"[{fmt_value(lo, fmt)}, {fmt_value(hi, fmt)}]",
        value=[lo, hi],
        derived=f"95 % cluster-bootstrap interval, metrics/{file}#{key}_lo/_hi",
    )


def _bin_label(name: str) -> str:
    """``z0-10m`` -> ``0–10 m``; ``z0p5-2m`` -> ``0.5–2 m``."""
    lo, hi = name[1:-1].replace("p", ".").split("-", 1)
    return f"{lo}–{hi} m"


def range_bins(src: page.Sources, group: str = "all") -> list[str]:
    """The range-bin names in ``disparity.json`` (e.g. ``z0-10m``), in the file's order."""
    data = src.metrics.get(DISPARITY_FILE) or {}
    pat = re.compile(rf"^{re.escape(group)}/(z[0-9p]+-[0-9p]+m)_relerr_median$")
    return [m.group(1) for k in data if (m := pat.match(k))]


def disparity_tables(src: page.Sources) -> list[Table]:
    """SGM disparity accuracy per group, then the relative depth error per range bin."""
    if not src.has(DISPARITY_FILE):
        return []
    groups = [g for g in GROUP_LABELS if src.get(DISPARITY_FILE, f"{g}/bad2") is not None]
    cols = [  # the metrics this file has (an older stage version wrote fewer)
        (m, label, f)
        for m, label, f in (
            ("bad2", "bad-2 (> 2 px)", "pct"),
            ("d1", "D1 (> 3 px and > 5 %)", "pct"),
            ("density", "density", "pct"),
            ("epe", "EPE [px]", "g4"),
        )
        if any(src.get(DISPARITY_FILE, f"{g}/{m}") is not None for g in groups)
    ]
    acc = Table(
        "SGM disparity accuracy against the exact disparity (reports/metrics/disparity.json)",
        ["pairs", *[label for _, label, _ in cols]],
        anchor="stereo-accuracy",
        note="Shares of the valid pixels with a GT surface; density = valid among GT pixels.",
    )
    for g in groups:
        acc.rows.append(
            [Cell(GROUP_LABELS[g])] + [src.cell(DISPARITY_FILE, f"{g}/{m}", f) for m, _, f in cols]
        )
    rng = Table(
        "SGM range error |Z − Z_gt| / Z_gt by GT distance (Z = fx·B / d; reports/metrics/disparity.json)",
        ["pairs", "GT distance", "GT pixels", "valid share", "median", "90th percentile"],
        anchor="stereo-range-error",
        note=(
            "Median and 90th percentile over the valid pixels of the bin; n/a in the 90th "
            "percentile: more than 10 % of the valid pixels are at 0 px (infinitely far)."
        ),
    )
    for g in [g for g in ("fault_none", "all") if g in groups]:
        for b in range_bins(src, g):
            rng.rows.append(
                [Cell(GROUP_LABELS[g]), Cell(_bin_label(b))]
                + [
                    src.cell(DISPARITY_FILE, f"{g}/{b}_{m}", f)
                    for m, f in (
                        ("gt_pixels", "int"),
                        ("valid_share", "pct"),
                        ("relerr_median", "pct"),
                        ("relerr_p90", "pct"),
                    )
                ]
            )
    tables = [acc] if acc.rows else []
    return tables + ([rng] if rng.rows else [])


def _speed_bins(src: page.Sources) -> list[str]:
    data = src.metrics.get(ORB_FILE) or {}
    pat = re.compile(r"^rule_orb/(delay_detection_v[0-9p]+-[0-9p]+)$")
    bins = [m.group(1) for k in data if (m := pat.match(k))]

    def lo(b: str) -> float:
        return float(b.removeprefix("delay_detection_v").split("-")[0].replace("p", "."))

    return sorted(bins, key=lo)


def _speed_label(b: str) -> str:
    lo, hi = b.removeprefix("delay_detection_v").replace("p", ".").split("-", 1)
    return f"v {lo}–{hi} m/s"


def fault_tables(src: page.Sources) -> list[Table]:
    """Detection / false-alarm rates per rule with intervals, delay detection by speed, the
    valid-share threshold sweep."""
    if not src.has(ORB_FILE):
        return []
    rules = [r for r in RULE_LABELS if src.get(ORB_FILE, f"rule_{r}/false_alarm") is not None]
    if not rules:  # an orb.json of an older stage version: the data section shows it
        return []
    tables = [_detection_table(src, rules), _pair_counts_table(src)]
    by_speed = _delay_by_speed_table(src, rules)
    sweep = _valid_share_sweep_table(src)
    return tables + [t for t in (by_speed, sweep) if t is not None]


def _detection_table(src: page.Sources, rules: list[str]) -> Table:
    """Delay / vertical-shift detection and false-alarm rates (%) per rule, with intervals."""
    t = Table(
        "Stereo-pair fault detection per rule (reports/metrics/orb.json)",
        [
            "rule",
            "drops pairs",
            "delay faults detected",
            "95 % CI",
            "vertical shifts detected",
            "95 % CI",
            "false alarms (fault-free)",
            "95 % CI",
        ],
        anchor="stereo-fault-detection",
        headline=True,
        note=(
            "Delay: the right image from a later time (paper: one game frame, 88 ms); vertical: "
            "the right image shifted vertically. 'drops pairs' marks the configured rule "
            "(risk_data.check.rule), the one that sets `outlier` in data/orb/orb.csv. Valid share "
            "= valid SGM pixels among the matchable columns; threshold "
            "risk_data.check.min_valid_share. " + CI_NOTE
        ),
    )
    for r in rules:
        pre = f"rule_{r}/"
        configured = src.get(ORB_FILE, f"{pre}configured")
        row = [Cell(RULE_LABELS[r]), Cell("yes" if configured == 1 else "")]
        for key in ("delay_detection", "vertical_detection", "false_alarm"):
            row += [src.cell(ORB_FILE, pre + key, "pct"), ci_cell(src, ORB_FILE, pre + key)]
        t.rows.append(row)
    return t


def _pair_counts_table(src: page.Sources) -> Table:
    """How many pairs each rate is over (with a delay fault, a vertical shift, fault-free)."""
    counts = Table(
        "Stereo-pair checks: pairs evaluated (reports/metrics/orb.json)",
        ["pairs", "count"],
        anchor="stereo-fault-counts",
    )
    for key, label in (
        ("delay_detection_n", "with a delay fault"),
        ("vertical_detection_n", "with a vertical shift"),
        ("false_alarm_n", "fault-free"),
    ):
        counts.rows.append([Cell(label), src.cell(ORB_FILE, f"rule_orb/{key}", "int")])
    return counts


def _delay_by_speed_table(src: page.Sources, rules: list[str]) -> Table | None:
    """Delay-fault detection (%) per rule and subject-speed bin (None without speed bins)."""
    bins = _speed_bins(src)
    if not bins:
        return None
    sp = Table(
        "Delay faults detected by subject speed (reports/metrics/orb.json)",
        ["rule", *[_speed_label(b) for b in bins]],
        anchor="stereo-delay-by-speed",
        note="A delayed right image of a standing subject differs only where others moved.",
    )
    sp.rows.append(
        [Cell("delay faults (count)")]
        + [src.cell(ORB_FILE, f"rule_orb/{b}_n", "int") for b in bins]
    )
    for r in rules:
        sp.rows.append(
            [Cell(RULE_LABELS[r])] + [src.cell(ORB_FILE, f"rule_{r}/{b}", "pct") for b in bins]
        )
    return sp


def _valid_share_sweep_table(src: page.Sources) -> Table | None:
    """False-alarm and detection rates (%) of the valid-share rule per threshold (None without
    a sweep)."""
    data = src.metrics.get(ORB_FILE) or {}
    pat = re.compile(r"^sweep/min_valid_share_([0-9p]+)_false_alarm_rate$")
    thresholds = [m.group(1) for k in data if (m := pat.match(k))]
    if not thresholds:
        return None
    sw = Table(
        "Valid-share rule: threshold sweep (reports/metrics/orb.json)",
        ["flag when valid share <", "false alarms", "delay detected", "vertical detected"],
        anchor="stereo-valid-share-sweep",
    )
    rates = ("false_alarm_rate", "delay_detection_rate", "vertical_detection_rate")
    for th in sorted(thresholds, key=lambda x: float(x.replace("p", "."))):
        pre = f"sweep/min_valid_share_{th}"
        sw.rows.append(
            [Cell(f"threshold {th.replace('p', '.')}")]
            + [src.cell(ORB_FILE, f"{pre}_{k}", "pct") for k in rates]
        )
    return sw


def resolution_tables(src: page.Sources) -> list[Table]:
    """The camera-resolution study: one column per width; the paired differences between widths."""
    data = src.metrics.get(RESOLUTION_FILE)
    if not isinstance(data, dict):
        return []
    widths = sorted({int(m.group(1)) for k in data if (m := re.match(r"^w(\d+)/", k))})
    if not widths:
        return []
    t = Table(
        "Camera resolution study: SGM range error at the critical distance and SGM cost "
        "(reports/metrics/stereo_resolution.json, benchmarks/stereo_resolution.py)",
        ["quantity", *[f"width {w} px" for w in widths]],
        anchor="stereo-resolution",
        note=(
            "Fault-free frames of seeded driving sequences rendered at each width (height = "
            "width / 2, same field of view and baseline); SGM search range scaled with the width. "
            "Critical distance: the 1.5 s headway at 8–14 m/s. Objects = pixels in front of the "
            "road plane. Times on the benchmark machine (median over frames). " + CI_NOTE
        ),
    )
    lo, hi = (
        json_number(data.get("study/critical_lo_m")),
        json_number(data.get("study/critical_hi_m")),
    )
    crit = f"{lo:g}–{hi:g} m" if lo is not None and hi is not None else "the critical distance"
    rows = [
        ("image height [px]", "height", "int", False),
        ("SGM search range [px]", "num_disparities", "int", False),
    ]
    rows += [
        (f"GT disparity at {z:g} m [px]", f"gt_disparity_px_at_{z:g}m", "f2", False)
        for z in (lo, hi)
        if z is not None
    ]
    rows += [
        (f"objects at {crit}: median range error", "crit_obj_relerr_median", "pct", True),
        (f"objects at {crit}: 90th percentile", "crit_obj_relerr_p90", "pct", False),
        (f"objects at {crit}: valid share", "crit_obj_valid_share", "pct", False),
        (f"all surfaces at {crit}: median range error", "crit_all_relerr_median", "pct", True),
        ("0–10 m: median range error", "z0-10m_relerr_median", "pct", False),
        ("10–30 m: median range error", "z10-30m_relerr_median", "pct", False),
        ("30–90 m: median range error", "z30-90m_relerr_median", "pct", False),
        ("30–90 m: 90th percentile", "z30-90m_relerr_p90", "pct", False),
        ("SGM time per frame [ms]", "sgm_ms_median", "f1", False),
        ("rendering time per frame [ms]", "render_ms_median", "f1", False),
    ]
    for label, key, fmt, with_ci in rows:
        t.rows.append(
            [Cell(label)] + [src.cell(RESOLUTION_FILE, f"w{w}/{key}", fmt) for w in widths]
        )
        if with_ci:
            t.rows.append(
                [Cell(f"{label}, 95 % CI")]
                + [ci_cell(src, RESOLUTION_FILE, f"w{w}/{key}") for w in widths]
            )
    diffs = [
        (k, m)
        for k in sorted(data)
        if (m := re.match(r"^diff_w(\d+)_minus_w(\d+)/(crit_obj|crit_all)_relerr_median$", k))
    ]
    if not diffs:
        return [t]
    d = Table(
        "Camera resolution study: paired difference of the median range error at the critical "
        "distance (reports/metrics/stereo_resolution.json)",
        ["pixels", "widths", "difference", "95 % CI"],
        anchor="stereo-resolution-difference",
        note="The same frames at both widths, scenarios resampled together. " + CI_NOTE,
    )
    for k, m in diffs:
        what = "objects" if m.group(3) == "crit_obj" else "all surfaces"
        d.rows.append(
            [
                Cell(f"{what} at {crit}"),
                Cell(f"width {m.group(1)} px − width {m.group(2)} px"),
                src.cell(RESOLUTION_FILE, k, "pct"),
                ci_cell(src, RESOLUTION_FILE, k),
            ]
        )
    return [t, d]


#: rows of the learned-stereo comparison: (label, metric key, format)
STEREO_ROWS = (
    ("end-point error [px]", "epe", "f3"),
    ("bad-1 (> 1 px)", "bad1", "pct"),
    ("bad-2 (> 2 px)", "bad2", "pct"),
    ("density (share of GT pixels with an estimate)", "density", "pct"),
    ("0–10 m: median range error", "z0-10m_relerr_median", "pct"),
    ("10–30 m: median range error", "z10-30m_relerr_median", "pct"),
    ("30–90 m: median range error", "z30-90m_relerr_median", "pct"),
    ("30–90 m: 90th percentile", "z30-90m_relerr_p90", "pct"),
    ("objects at the critical distances: median range error", "crit_obj_relerr_median", "pct"),
    ("objects at the critical distances: 90th percentile", "crit_obj_relerr_p90", "pct"),
    ("objects at the critical distances: share estimated", "crit_obj_density", "pct"),
)
MASK_LABELS = {
    "common": "pixels both sources estimate",
    "own": "each source's own estimated pixels",
}


def learned_tables(src: page.Sources) -> list[Table]:
    """SGM vs the learned stereo network on the test split (both masks), their paired
    differences and the targets of the learned stereo."""
    if not src.has(STEREO_FILE):
        return []
    out = []
    for mask, what in MASK_LABELS.items():
        t = Table(
            f"Learned stereo network vs SGM, fault-free test frames, {what} "
            "(reports/metrics/stereo.json)",
            ["quantity", "SGM", "SGM 95 % CI", "learned", "learned 95 % CI"],
            anchor=f"stereo-learned-{mask}",
            note=(
                "Relative range error |Z − Z_gt| / Z_gt; critical distances: objects (pixels in "
                "front of the road plane) at 12–21 m, the 1.5 s headway at 8–14 m/s. " + CI_NOTE
            ),
        )
        for label, key, fmt in STEREO_ROWS:
            if mask == "common" and key == "density":
                continue  # the common mask's density is the same for both by construction
            t.rows.append(
                [Cell(label)]
                + [
                    c
                    for source in ("sgm", "learned")
                    for c in (
                        src.cell(STEREO_FILE, f"{source}/{mask}/{key}", fmt),
                        ci_cell(src, STEREO_FILE, f"{source}/{mask}/{key}", fmt),
                    )
                ]
            )
        out.append(t)
    d = Table(
        "Learned stereo network − SGM, paired on the same test frames (reports/metrics/stereo.json)",
        ["pixels", "quantity", "difference", "95 % CI"],
        anchor="stereo-learned-difference",
        note="Sequences resampled together for both sources. " + CI_NOTE,
    )
    for mask, what in MASK_LABELS.items():
        for label, key, fmt in (
            ("end-point error [px]", "epe", "f3"),
            ("critical objects: median range error", "crit_obj_relerr_median", "pct"),
        ):
            k = f"diff_learned_minus_sgm/{mask}/{key}"
            d.rows.append(
                [
                    Cell(what),
                    Cell(label),
                    src.cell(STEREO_FILE, k, fmt),
                    ci_cell(src, STEREO_FILE, k, fmt),
                ]
            )
    out.append(d)
    out.extend(generalisation_tables(src))
    targets = src.get(STEREO_FILE, "targets")
    if isinstance(targets, dict) and targets:
        tt = Table(
            "Learned stereo: targets (default profile, fault-free test frames)",
            ["target", "value", "95 % CI", "op", "threshold", "met", "description"],
            anchor="stereo-learned-targets",
            note=(
                "met: the point estimate against the threshold; a difference target is met only "
                "when its whole interval lies on the target's side. " + CI_NOTE
            ),
        )
        for name in targets:
            fmt = str(src.get(STEREO_FILE, f"targets.{name}.format") or "g4")
            tt.rows.append(
                [
                    Cell(name),
                    src.cell(STEREO_FILE, f"targets.{name}.value", fmt),
                    ci_cell(src, STEREO_FILE, f"targets.{name}.value", fmt)
                    if src.get(STEREO_FILE, f"targets.{name}.value_lo") is not None
                    else Cell(NA),
                    src.cell(STEREO_FILE, f"targets.{name}.op"),
                    src.cell(STEREO_FILE, f"targets.{name}.threshold", fmt),
                    src.cell(STEREO_FILE, f"targets.{name}.met"),
                    src.cell(STEREO_FILE, f"targets.{name}.description"),
                ]
            )
        out.append(tt)
    return out


VARIANTS_FILE = "sgm_variants.json"
#: the SGM variants table's columns: (header, figure key, format)
VARIANT_COLUMNS = (
    ("EPE [px]", "epe", "f3"),
    ("bad-1", "bad1", "pct"),
    ("density", "density", "pct"),
    ("critical objects: median range error", "crit_obj_relerr_median", "pct"),
    ("critical objects: p90", "crit_obj_relerr_p90", "pct"),
    ("critical objects: share estimated", "crit_obj_density", "pct"),
)
#: how many variants the table lists beyond the configured and the chosen one
VARIANTS_SHOWN = 6


def variant_tables(src: page.Sources) -> list[Table]:
    """SGM variants on validation (the configured matcher, the chosen one and the best others by
    the rule's criterion) and the chosen one against the configured matcher on test
    (``sgm_variants.json``)."""
    figs = src.get(VARIANTS_FILE, "validation.variants")
    if not isinstance(figs, dict) or not figs:
        return []
    chosen = str(src.get(VARIANTS_FILE, "choice.chosen"))
    configured = str(src.get(VARIANTS_FILE, "choice.configured"))
    guard = figs.get(configured, {}).get("crit_obj_density")

    def crit(name: str) -> float:
        v = figs[name].get("crit_obj_relerr_median")
        return float(v) if isinstance(v, (int, float)) else float("inf")

    others = sorted((n for n in figs if n not in (chosen, configured)), key=crit)
    names = [configured] + ([chosen] if chosen != configured else []) + others[:VARIANTS_SHOWN]
    t = Table(
        f"SGM variants on {src.get(VARIANTS_FILE, 'validation.frames')} fault-free validation "
        f"frames, each variant's own estimated pixels ({len(figs)} scored; "
        "reports/metrics/sgm_variants.json)",
        ["variant", "role"] + [h for h, _, _ in VARIANT_COLUMNS],
        anchor="stereo-sgm-variants",
        note=(
            f"Rule, fixed before scoring: {src.get(VARIANTS_FILE, 'choice.rule')}. Variant names: "
            "block size (bs, px), uniqueness ratio (ur, %), speckle window (sw, px; 0 = off), colour "
            "or grey matching; the search range is the configured one. The listed others are the "
            "best by the criterion; 'below the density guard' ones could not be chosen."
        ),
    )
    for n in names:
        role = (
            "configured and chosen"
            if n == chosen == configured
            else "configured"
            if n == configured
            else "chosen"
            if n == chosen
            else "below the density guard"
            if isinstance(guard, (int, float))
            and isinstance(figs[n].get("crit_obj_density"), (int, float))
            and figs[n]["crit_obj_density"] < guard
            else ""
        )
        t.rows.append(
            [Cell(n), Cell(role)]
            + [
                src.cell(VARIANTS_FILE, f"validation.variants.{n}.{k}", fmt)
                for _, k, fmt in VARIANT_COLUMNS
            ]
        )
    out = [t]
    why = src.get(VARIANTS_FILE, "test.why")
    if why:
        t.note += f" Test split: {why}."
        return out
    c = Table(
        f"SGM: the chosen variant ({chosen}) vs the configured matcher ({configured}) on the "
        "fault-free test frames, each one's own estimated pixels (reports/metrics/sgm_variants.json)",
        ["quantity", "configured", "configured 95 % CI", "chosen", "chosen 95 % CI"],
        anchor="stereo-sgm-chosen",
        note=(
            f"{src.get(VARIANTS_FILE, 'test.test/frames')} frames of "
            f"{src.get(VARIANTS_FILE, 'test.test/sequences')} sequences; the paired differences "
            "(chosen − configured, same frames, pixels both estimate) in the last rows. " + CI_NOTE
        ),
    )
    for label, key, fmt in GENERALISATION_ROWS:
        c.rows.append(
            [Cell(label)]
            + [
                x
                for source in ("configured", "chosen")
                for x in (
                    src.cell(VARIANTS_FILE, f"test.{source}/own/{key}", fmt),
                    ci_cell(src, VARIANTS_FILE, f"test.{source}/own/{key}", fmt),
                )
            ]
        )
    for label, key, fmt in (
        ("chosen − configured: end-point error [px]", "epe", "f3"),
        (
            "chosen − configured: critical objects median range error",
            "crit_obj_relerr_median",
            "pct",
        ),
    ):
        k = f"test.diff_chosen_minus_configured/common/{key}"
        c.rows.append(
            [
                Cell(label),
                Cell(""),
                Cell(""),
                src.cell(VARIANTS_FILE, k, fmt),
                ci_cell(src, VARIANTS_FILE, k, fmt),
            ]
        )
    out.append(c)
    return out


#: the generalisation table's rows: (label, metric key, format), on each source's own pixels
GENERALISATION_ROWS = (
    ("end-point error [px]", "epe", "f3"),
    ("bad-1 (> 1 px)", "bad1", "pct"),
    ("objects at the critical distances: median range error", "crit_obj_relerr_median", "pct"),
    ("objects at the critical distances: 90th percentile", "crit_obj_relerr_p90", "pct"),
)
GENERALISATION_SOURCES = {"sgm": "SGM", "learned": "full network", "holdout": "without them"}


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
    t = Table(
        title,
        ["quantity"] + [h for v in GENERALISATION_SOURCES.values() for h in (v, f"{v} 95 % CI")],
        anchor="stereo-generalisation",
        note=(
            "'without them': the same network and training without these templates' frames "
            "(stage train_stereo_holdout); 'full network': the model that is evaluated above. "
            f"{g.get('test/frames')} frames of {g.get('test/sequences')} sequences. " + CI_NOTE
        ),
    )
    for label, key, fmt in GENERALISATION_ROWS:
        t.rows.append(
            [Cell(label)]
            + [
                c
                for source in GENERALISATION_SOURCES
                for c in (
                    src.cell(STEREO_FILE, f"generalisation.{source}/own/{key}", fmt),
                    ci_cell(src, STEREO_FILE, f"generalisation.{source}/own/{key}", fmt),
                )
            ]
        )
    d = Table(
        f"Learned stereo without the templates {names} − with them, and − SGM, paired on the "
        "same frames (reports/metrics/stereo.json)",
        ["difference", "pixels", "quantity", "value", "95 % CI"],
        anchor="stereo-generalisation-difference",
        note="A positive difference: the network that never saw the templates is worse. " + CI_NOTE,
    )
    for other, what in (("learned", "without − full network"), ("sgm", "without − SGM")):
        for mask, pixels in MASK_LABELS.items():
            for label, key, fmt in (
                ("end-point error [px]", "epe", "f3"),
                ("critical objects: median range error", "crit_obj_relerr_median", "pct"),
            ):
                k = f"generalisation.diff_holdout_minus_{other}/{mask}/{key}"
                d.rows.append(
                    [
                        Cell(what),
                        Cell(pixels),
                        Cell(label),
                        src.cell(STEREO_FILE, k, fmt),
                        ci_cell(src, STEREO_FILE, k, fmt),
                    ]
                )
    return [t, d]


def section(src: page.Sources, figures: list[page.Figure]) -> page.Section:
    """The stereo section: disparity and range accuracy, fault detection, resolution study."""
    sec = page.Section(TITLE)
    sec.paragraphs.append(
        "SGM (OpenCV StereoSGBM, 8 paths, left-right check, speckle filter) on every stereo pair, "
        "scored against the exact disparity; a disparity error says little at small disparities, "
        "so the range error is shown per distance bin. Broken stereo pairs are caught by the "
        "paper's ORB rule (Sec. 3.3), a robust variant of it, and the share of valid SGM pixels. "
        "A learned stereo network (cost volume, soft-argmin, edge-aware refinement; stage "
        "train_stereo, trained on the training sequences' exact disparity) is scored beside SGM "
        "on the same test frames (stage stereo_learned); its pixels whose disparity distribution "
        "is wider than a threshold chosen on validation count as 'no estimate'."
    )
    sec.tables.extend(disparity_tables(src))
    sec.tables.extend(learned_tables(src))
    sec.tables.extend(variant_tables(src))
    sec.tables.extend(fault_tables(src))
    res = resolution_tables(src)
    sec.tables.extend(res)
    for file, what in (
        (DISPARITY_FILE, "disparity"),
        (STEREO_FILE, "stereo_learned"),
        (VARIANTS_FILE, "sgm_variants"),
        (ORB_FILE, "orb_filter"),
    ):
        if not src.has(file):
            sec.paragraphs.append(f"`reports/metrics/{file}` is missing: stage {what} has not run.")
    if not res:
        sec.paragraphs.append(
            f"`reports/metrics/{RESOLUTION_FILE}` is missing: run "
            "`python -m benchmarks.stereo_resolution`."
        )
    sec.figures = figures
    return sec


def provider() -> page.SectionProvider:
    """The stereo section's provider for the report (after the risk section)."""
    return page.SectionProvider(
        name="stereo",  # its page, reports/pages/stereo.md (no headline numbers)
        section=section,
        figures=FIGURES,
        figure_pattern=NEVER,
        shown_files=r"stereo_resolution\.json|stereo\.json|sgm_variants\.json",
    )
