"""The twin's part of the report: how often the ego's risk read from the twin flags the truly
critical frames, compared with its own map, in occluded and open sequences, with the targets.

Reads ``twin.json`` (stage evaluate_twin, layout :mod:`traffictwin.twin.evaluation`:
``configurations.<cfg>.methods.<method>.<kind>.<metric>`` with ``<metric>_ci = [lo, hi]``, and
``targets``) and ``twin_data.json`` (stage generate_twin). A missing file or key is an ``n/a``
cell, never an error. Entry point: :func:`provider`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from traffictwin.report import model as page
from traffictwin.report.model import NA, Cell, DataFile, Table, fmt_value, lookup
from traffictwin.report.summary import Headline, headline, strongest
from traffictwin.risk.report_tables import RISK_FILE

FILE = "twin.json"
DATA_FILE = "twin_data.json"
TITLE = "Cooperative twin — risk from N vehicles' fused maps"
FIGURES: dict[str, str] = {
    "twin_timeline": (
        "Time headway of the ego over a typical occluded sequence (the twin's lead over the ego "
        "closest to the median) at the target configuration: from its "
        "own map, from the twin and the truth; shaded = truly critical (THW < twin.critical_thw), "
        "dashed = the warning level (twin.critical_thw + twin.reaction_s), ticks = "
        "frames in which the ego's own lidar returns from the hazard"
    ),
    "twin_map": (
        "The twin at the critical onset of that sequence (ego frame) and each vehicle's map where "
        "the twin put it; true and noisy positions with the configuration's 98 % radius"
    ),
}
LABELS = {
    "ego": "ego's own map (no cooperation)",
    "naive": "naive (noisy poses + Dempster)",
    "registered": "registered (FM + ECC) + Dempster",
    "learned": "learned registration + Dempster",
    "dnn": "network on noisy poses",
    "registered+network": "registered + network",
    "learned+network": "learned registration + network",
}


def critical_thw_text(src: page.Sources) -> str:
    """The critical THW as text (e.g. ``"1 s"``): the primary ``thresholds_s`` of ``risk.json``
    (``twin.critical_thw`` interpolates it); the key's name when that file lacks it."""
    ts = src.get(RISK_FILE, "thresholds_s")
    return f"{float(ts[0]):g} s" if isinstance(ts, list) and ts else "twin.critical_thw"


def note(src: page.Sources) -> str:
    """What the warning tables measure, at the run's critical THW (:func:`critical_thw_text`)."""
    crit = critical_thw_text(src)
    return (
        "Frames are critical when the true time headway (corridor, vehicles and pedestrians, "
        f"simulator boxes) is below {crit}; a map warns (flags a frame) when the headway read "
        "from its occupied cells (m_O >= twin.occ_threshold, the ego's footprint ignored) is "
        f"below {crit} + twin.reaction_s (1 s: a warning leaves the driver a reaction time "
        "before the episode). Lead: per critical episode, onset minus the first warning from "
        "twin.horizon_s before the onset (never = one frame after the episode); 'lead over ego' "
        "pairs it with the ego map's on the same episode (median). Intervals: 95 % bootstrap "
        "over sequences (traffictwin.stats)."
    )


ALWAYS_LABEL = "reference: a warning at every frame"
ALWAYS_NOTE = (
    " The reference row warns at every frame (a constant, not a method): its lead is the most "
    "the definition allows (twin.horizon_s, less where a sequence starts later), so a method's "
    "lead is read beside its false alarms."
)


def _ci(src: page.Sources, key: str, fmt: str) -> Cell:
    v = src.get(FILE, key)
    if not (isinstance(v, list) and len(v) == 2 and all(isinstance(x, (int, float)) for x in v)):
        return Cell(NA, title=f"no interval in reports/metrics/{FILE}: {key}")
    return Cell(
        f"[{fmt_value(v[0], fmt)}, {fmt_value(v[1], fmt)}]",
        value=list(v),
        derived=f"95 % sequence-bootstrap interval, metrics/{FILE}#{key}",
    )


def _methods(src: page.Sources, c: str) -> list[str]:
    m = src.get(FILE, f"configurations.{c}.methods")
    return list(m) if isinstance(m, dict) else []


def occluded_table(src: page.Sources) -> Table:
    cols = [
        "config",
        "map the ego reads",
        "critical frames flagged",
        "95 % CI",
        "Δ vs ego map",
        "95 % CI",
        "median lead over ego (s)",
        "95 % CI",
        "warned before onset",
        "vehicles left out",
    ]
    t = Table(
        "Twin: critical frames flagged in occluded sequences",
        cols,
        anchor="twin-occluded",
    )
    configs = src.get(FILE, "configurations")
    for c in configs if isinstance(configs, dict) else {}:
        for m in _methods(src, c):
            k = f"configurations.{c}.methods.{m}.occluded"
            row = [
                Cell(c),
                Cell(LABELS.get(m, m)),
                src.cell(FILE, f"{k}.recall", "pct"),
                _ci(src, f"{k}.recall_ci", "pct"),
            ]
            if m == "ego":
                row += [Cell("—")] * 4
                row += [src.cell(FILE, f"{k}.warned_before_onset_share", "pct"), Cell("—")]
            else:
                row += [
                    src.cell(FILE, f"{k}.recall_vs_ego", "pct"),
                    _ci(src, f"{k}.recall_vs_ego_ci", "pct"),
                    src.cell(FILE, f"{k}.lead_vs_ego_s_median", "f2"),
                    _ci(src, f"{k}.lead_vs_ego_s_median_ci", "f2"),
                    src.cell(FILE, f"{k}.warned_before_onset_share", "pct"),
                    src.cell(FILE, f"{k}.left_out_share", "pct"),
                ]
            t.rows.append(row)
        k = f"configurations.{c}.always_warns.occluded"
        if isinstance(src.get(FILE, k), dict):
            t.rows.append(
                [Cell(c), Cell(ALWAYS_LABEL)]
                + [Cell("—")] * 4
                + [
                    src.cell(FILE, f"{k}.lead_vs_ego_s_median", "f2"),
                    _ci(src, f"{k}.lead_vs_ego_s_median_ci", "f2"),
                    src.cell(FILE, f"{k}.warned_before_onset_share", "pct"),
                    Cell("—"),
                ]
            )
    t.note = note(src) + ALWAYS_NOTE
    return t


def open_table(src: page.Sources) -> Table:
    cols = [
        "config",
        "map the ego reads",
        "critical frames flagged",
        "95 % CI",
        "false alarms (frames)",
        "95 % CI",
        "false alarms / min",
        "under pose bias (frames)",
        "95 % CI",
    ]
    t = Table(
        "Twin: open sequences (nothing hidden) — recall and false alarms", cols, anchor="twin-open"
    )
    configs = src.get(FILE, "configurations")
    for c in configs if isinstance(configs, dict) else {}:
        for m in _methods(src, c):
            k = f"configurations.{c}.methods.{m}.open"
            kb = f"configurations.{c}.pose_bias.methods.{m}.open"
            t.rows.append(
                [
                    Cell(c),
                    Cell(LABELS.get(m, m)),
                    src.cell(FILE, f"{k}.recall", "pct"),
                    _ci(src, f"{k}.recall_ci", "pct"),
                    src.cell(FILE, f"{k}.false_alarm_share", "pct"),
                    _ci(src, f"{k}.false_alarm_share_ci", "pct"),
                    src.cell(FILE, f"{k}.false_alarms_per_min", "f2"),
                    src.cell(FILE, f"{kb}.false_alarm_share", "pct"),
                    _ci(src, f"{kb}.false_alarm_share_ci", "pct"),
                ]
            )
        k = f"configurations.{c}.always_warns.open"
        if isinstance(src.get(FILE, k), dict):
            t.rows.append(
                [Cell(c), Cell(ALWAYS_LABEL), Cell("—"), Cell("—")]
                + [
                    src.cell(FILE, f"{k}.false_alarm_share", "pct"),
                    _ci(src, f"{k}.false_alarm_share_ci", "pct"),
                    src.cell(FILE, f"{k}.false_alarms_per_min", "f2"),
                    Cell("—"),
                    Cell("—"),
                ]
            )
    t.note = (
        "False alarms: warnings with no critical frame within twin.horizon_s, as a share of the "
        "judged frames and as runs per minute of judged driving (a warning in a sequence's last "
        "twin.horizon_s with no critical frame up to its end is right-censored: what it announces "
        "may start after the recording, so it is not judged); 'under pose bias': each vehicle's pose error "
        "persists over the sequence (twin.bias_share of its variance) besides per-frame jitter. "
        "Intervals: 95 % bootstrap over sequences (traffictwin.stats)."
    )
    return t


HAZARD_LABELS = {
    "pedestrian": "pedestrian steps out behind a van (ego turns right)",
    "emerging_car": "car pulls out of a driveway behind a truck and hedge (ego straight)",
    "stopped_car": "car stopped beside a van (ego turns right)",
}


def hazard_table(src: page.Sources) -> Table:
    """Per hazard kind and scenario kind: each method's episodes, median lead over the ego's map,
    episodes warned before the onset and false-alarm frames (``by_hazard`` of twin.json)."""
    cols = [
        "config",
        "scenario",
        "hazard",
        "map the ego reads",
        "episodes",
        "median lead over ego (s)",
        "95 % CI",
        "warned before onset",
        "false alarms (frames)",
        "95 % CI",
    ]
    t = Table("Twin: each hazard kind separately", cols, anchor="twin-hazards")
    configs = src.get(FILE, "configurations")
    for c in configs if isinstance(configs, dict) else {}:
        for kind in ("occluded", "open"):
            for m in _methods(src, c):
                hz = src.get(FILE, f"configurations.{c}.methods.{m}.{kind}.by_hazard")
                for h in sorted(hz) if isinstance(hz, dict) else ():
                    k = f"configurations.{c}.methods.{m}.{kind}.by_hazard.{h}"
                    lead = [Cell("—")] * 2
                    if m != "ego":
                        lead = [
                            src.cell(FILE, f"{k}.lead_vs_ego_s_median", "f2"),
                            _ci(src, f"{k}.lead_vs_ego_s_median_ci", "f2"),
                        ]
                    t.rows.append(
                        [
                            Cell(c),
                            Cell(kind),
                            Cell(HAZARD_LABELS.get(h, h)),
                            Cell(LABELS.get(m, m)),
                            src.cell(FILE, f"{k}.episodes", "int"),
                            *lead,
                            src.cell(FILE, f"{k}.warned_before_onset_share", "pct"),
                            src.cell(FILE, f"{k}.false_alarm_share", "pct"),
                            _ci(src, f"{k}.false_alarm_share_ci", "pct"),
                        ]
                    )
    t.note = (
        "The targets are on all occluded / open sequences (tables above); this splits them "
        "by what hides: about half the sequences of each kind per hazard (twin_data.json), so the "
        "intervals are wider. " + note(src)
    )
    return t


TARGETS = (
    ("occluded_recall_ge_0.9", "occluded: twin flags >= 90 % of critical frames", "pct"),
    ("occluded_recall_above_ego", "occluded: twin flags more than the ego map (CI > 0)", "pct"),
    (
        "occluded_median_lead_vs_ego_ge_0.8s",
        "occluded: median lead over the ego map >= 0.8 s (CI > 0)",
        "f2",
    ),
    (
        "occluded_warned_before_onset_ge_0.95",
        "occluded: >= 95 % of episodes warned before onset",
        "pct",
    ),
    ("open_false_alarms_le_0.05_frame_noise", "open: false alarms <= 5 % of frames", "pct"),
    (
        "open_false_alarms_le_0.05_pose_bias",
        "open, persistent pose bias: false alarms <= 5 % of frames",
        "pct",
    ),
    ("registration_lead_above_naive", "occluded: mean lead over the naive twin (CI > 0)", "f2"),
    (
        "registration_false_alarms_below_naive_frame_noise",
        "open: false alarms minus the naive twin's (CI < 0)",
        "pct",
    ),
    (
        "registration_false_alarms_below_naive_pose_bias",
        "open, pose bias: false alarms minus the naive twin's (CI < 0)",
        "pct",
    ),
    (
        "predictive_warns_earlier_than_thw",
        "all kinds: predictive (TTC) warning minus THW's lead, same maps (mean s, CI > 0)",
        "f2",
    ),
    (
        "predictive_no_more_false_alarms",
        "open: predictive minus THW false alarms, same frames (CI includes or below 0)",
        "pct",
    ),
)


def predictive_table(src: page.Sources) -> Table:
    cols = [
        "config",
        "map the ego reads",
        "kind",
        "lead vs THW (mean s)",
        "95 % CI",
        "warned before onset (TTC)",
        "false alarms (TTC)",
        "Δ false alarms vs THW",
        "95 % CI",
        "true-TTC frames warned",
    ]
    t = Table(
        "Twin: predictive warnings (time to conflict) vs THW warnings on the same maps",
        cols,
        anchor="twin-predictive",
    )
    configs = src.get(FILE, "configurations")
    for c in configs if isinstance(configs, dict) else {}:
        for m in _methods(src, c):
            for kind in ("occluded", "open"):
                k = f"configurations.{c}.methods.{m}.{kind}.predictive"
                t.rows.append(
                    [
                        Cell(c),
                        Cell(LABELS.get(m, m)),
                        Cell(kind),
                        src.cell(FILE, f"{k}.lead_vs_thw_s_mean", "f2"),
                        _ci(src, f"{k}.lead_vs_thw_s_mean_ci", "f2"),
                        src.cell(FILE, f"{k}.warned_before_onset_share", "pct"),
                        src.cell(FILE, f"{k}.false_alarm_share", "pct"),
                        src.cell(FILE, f"{k}.false_alarm_share_vs_thw", "pct"),
                        _ci(src, f"{k}.false_alarm_share_vs_thw_ci", "pct"),
                        src.cell(FILE, f"{k}.ttc_true_recall", "pct"),
                    ]
                )
    t.note = (
        "Time to conflict (traffictwin.twin.predict): the motion of the occupied components "
        "tracked between consecutive maps of the same source (ego motion compensated), "
        "extrapolated at constant velocity (points behind the ego excluded); the earliest time a "
        "predicted occupied cell is in the ego's swept corridor. A map warns predictively when it "
        "stays below the level of the rule chosen on the validation sequences (next table: "
        "twin.ttc_warn_s + twin.reaction_s or a candidate level); lead and false alarms as for "
        "THW, against the "
        f"same critical episodes (true THW < {critical_thw_text(src)}), paired with the THW "
        "warnings of the same maps. "
        "'True-TTC frames warned': share of the frames whose TTC on the simulator's boxes and "
        "velocities is below that threshold. Intervals: 95 % bootstrap over sequences."
    )
    return t


def rule_table(src: page.Sources) -> Table:
    """The predictive rule's candidates on the validation sequences, and the one chosen."""
    n = src.get(FILE, "predictive_rule.validation_sequences")
    cols = [
        "warns below TTC (s)",
        "confirmed over (frames)",
        "lead vs THW (mean s)",
        "Δ false alarms vs THW (open)",
        "eligible",
        "chosen",
    ]
    t = Table(
        f"Twin: the predictive rule, chosen on {n if n is not None else NA} validation sequences",
        cols,
        anchor="twin-predictive-rule",
    )
    rows = src.get(FILE, "predictive_rule.candidates")
    for name in rows if isinstance(rows, dict) else {}:
        k = f"predictive_rule.candidates.{name}"
        yes_no = {True: "yes", False: "no"}
        t.rows.append(
            [
                src.cell(FILE, f"{k}.warn_s", "f2"),
                src.cell(FILE, f"{k}.confirm_frames", "int"),
                src.cell(FILE, f"{k}.lead_vs_thw_s_mean", "f2"),
                src.cell(FILE, f"{k}.false_alarm_share_vs_thw", "pct"),
                Cell(yes_no.get(src.get(FILE, f"{k}.eligible"), NA)),
                Cell(yes_no.get(src.get(FILE, f"{k}.selected"), NA)),
            ]
        )
    t.note = (
        "Chosen before any evaluated sequence is read, on the twin data's validation split (the "
        "headline twin at the target configuration, per-frame noise), by a criterion fixed "
        "beforehand: of the candidates whose predictive warning leads the THW warning of the same "
        "maps (mean over critical episodes > 0 s), the fewest false alarms beyond THW's in open "
        "sequences. A TTC warns when it stays below the level for the confirming frames "
        "(traffictwin.twin.predictive_rule); the predictive tables above use the chosen rule."
    )
    return t


def vehicle_table(src: page.Sources) -> Table:
    """Risk for every other vehicle: its own map vs its view of each twin (all sequences)."""
    cols = [
        "config",
        "vehicle",
        "map it reads",
        "critical frames",
        "critical frames flagged",
        "95 % CI",
        "Δ vs own map",
        "95 % CI",
        "false alarms (frames)",
        "95 % CI",
    ]
    t = Table("Twin: risk for every other vehicle", cols, anchor="twin-vehicles")
    configs = src.get(FILE, "configurations")
    for c in configs if isinstance(configs, dict) else {}:
        vehicles = src.get(FILE, f"configurations.{c}.vehicles")
        for k, entry in (vehicles if isinstance(vehicles, dict) else {}).items():
            for m in entry.get("methods", {}):
                key = f"configurations.{c}.vehicles.{k}.methods.{m}.all"
                own = m == "own"
                t.rows.append(
                    [
                        Cell(c),
                        Cell(f"{k} ({entry.get('role', NA)})"),
                        Cell("its own map" if own else LABELS.get(m, m)),
                        src.cell(FILE, f"{key}.critical_frames", "int"),
                        src.cell(FILE, f"{key}.recall", "pct"),
                        _ci(src, f"{key}.recall_ci", "pct"),
                        Cell("—") if own else src.cell(FILE, f"{key}.recall_vs_ego", "pct"),
                        Cell("—") if own else _ci(src, f"{key}.recall_vs_ego_ci", "pct"),
                        src.cell(FILE, f"{key}.false_alarm_share", "pct"),
                        _ci(src, f"{key}.false_alarm_share_ci", "pct"),
                    ]
                )
    t.note = (
        "Every other vehicle reads the same time headway along its own lane ahead, against its own "
        "truth (simulator boxes), from its own map and from its view of each twin: its own map "
        "fused with every map the twin used, placed in its frame by the twin's poses "
        "(traffictwin.twin.vehicle_view; a vehicle the twin left out sees only its own map). "
        "Per-frame pose noise, occluded and open sequences together; the hazards are placed for "
        "the ego, so the others' critical frames are mostly a follower's short headway to the "
        "ego ahead. False alarms as for the ego. Intervals: 95 % bootstrap over sequences."
    )
    return t


def targets_table(src: page.Sources) -> Table:
    c = src.get(FILE, "targets.configuration")
    m = src.get(FILE, "targets.method")
    t = Table(
        f"Twin targets (configuration {c if c is not None else NA}, twin: {m if m is not None else NA})",
        ["target", "value", "95 % CI", "met"],
        anchor="twin-targets",
        headline=True,
    )
    for key, label, fmt in TARGETS:
        ok = src.get(FILE, f"targets.{key}.met")
        t.rows.append(
            [
                Cell(label),
                src.cell(FILE, f"targets.{key}.value", fmt),
                _ci(src, f"targets.{key}.ci", fmt),
                Cell(
                    NA if ok is None else ("yes" if ok else "no"),
                    value=ok,
                    derived=f"metrics/{FILE}#targets.{key}.met",
                ),
            ]
        )
    key = "targets.registration_lead_above_naive"
    v, ci = src.get(FILE, f"{key}.always_warns_value"), src.get(FILE, f"{key}.always_warns_ci")
    if isinstance(v, (int, float)) and isinstance(ci, list) and len(ci) == 2:
        verdict = "is met by a constant" if ci[0] > 0 else "is not met by a constant"
        t.note = (
            f"The lead over the naive twin {verdict}: a warning at every frame leads "
            f"the naive twin by {fmt_value(v, 'f2')} s [{fmt_value(ci[0], 'f2')}, "
            f"{fmt_value(ci[1], 'f2')}] on the same episodes (metrics/{FILE}#{key}.always_warns_value). "
            "A lead is earned only with few false alarms: read it beside the false-alarm rows."
        )
    return t


def section(src: page.Sources, figures: list[page.Figure]) -> page.Section:
    paras = [
        "Three vehicles share lidar evidential maps at 10 Hz around a junction (stage generate_twin). "
        "Two hazard kinds: the ego turns right towards a pedestrian who steps out from behind a van "
        "parked at the kerb, or drives straight past a truck parked at the kerb, behind which a car "
        "pulls out of a driveway hidden by a hedge. In `occluded` sequences the hazard is hidden "
        "from the ego for twin.hidden_s up to the critical onset (and seen by another vehicle); in "
        "`open` ones the van or truck is parked at the far kerb and no hedge stands. Every vehicle's pose "
        "carries the configuration's noise, drawn per frame or as a persistent bias; the twin "
        "registers the others' maps onto the ego's (stage evaluate_twin) and the ego's time headway "
        "is read from its own map and from the twin. Warnings are scored per critical episode: lead "
        "from the first warning within twin.horizon_s before the onset, false alarms = warnings with "
        "no episode within the horizon. Beside the time headway, a predictive measure — the time to "
        "conflict with the motion estimated from consecutive maps — warns from the same maps. See "
        "the tables for what the twin gains and costs."
    ]
    if not src.has(FILE):
        paras.append(f"reports/metrics/{FILE} is missing: run `dvc repro evaluate_twin`.")
        return page.Section(TITLE, paragraphs=paras, figures=figures)
    return page.Section(
        TITLE,
        paragraphs=paras,
        tables=[
            occluded_table(src),
            open_table(src),
            hazard_table(src),
            predictive_table(src),
            rule_table(src),
            vehicle_table(src),
            targets_table(src),
        ],
        figures=figures,
    )


def headlines(metrics: Mapping[str, Any]) -> list[Headline]:
    """The targets' method and configuration, occluded sequences: share of critical frames
    flagged (``recall``) and its gain over the ego's own map (``recall_gain``), with their
    sequence-bootstrap intervals."""
    twin = metrics.get(FILE)
    method = lookup(twin, "targets.method") or lookup(twin, "headline")
    cfg = lookup(twin, "targets.configuration")
    occ = lookup(twin, f"configurations.{cfg}.methods.{method}.occluded")
    if not isinstance(occ, Mapping):
        return []
    where = f"{LABELS.get(method, method)} at configuration {cfg}, occluded sequences"
    others = lookup(twin, f"configurations.{cfg}.methods")
    base = strongest(
        {
            LABELS.get(m, m): (
                lookup(row, "occluded.recall"),
                lookup(row, "occluded.recall_ci"),
                f"metrics/{FILE}#configurations.{cfg}.methods.{m}.occluded.recall",
            )
            for m, row in (others.items() if isinstance(others, Mapping) else ())
            if m != method
        },
        higher_better=True,
    )
    return headline(
        "recall",
        "critical frames flagged",
        where,
        occ.get("recall"),
        occ.get("recall_ci"),
        "pct",
        base,
    ) + headline(
        "recall_gain",
        "gain in critical frames flagged over the ego's own map",
        where,
        occ.get("recall_vs_ego"),
        occ.get("recall_vs_ego_ci"),
        "pct",
    )


def provider() -> page.SectionProvider:
    """The twin section's provider for the report (after the fusion and risk sections)."""
    return page.SectionProvider(
        name="twin",
        headlines=headlines,
        section=section,
        figures=FIGURES,
        data_files=(DataFile(DATA_FILE, "Twin data (generate_twin)"),),
        shown_files=r"twin\.json",
    )
