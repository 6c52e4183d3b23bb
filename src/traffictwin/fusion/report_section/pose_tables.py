"""The fusion section's registration tables: the pose error of every row that estimates a pose
(per configuration) and its success rate per bin of the drawn translation and yaw error."""

from __future__ import annotations

from collections.abc import Sequence

from traffictwin.fusion.report_section.cells import (
    CI_NOTE,
    FUSION_FILE,
    POSE_ROWS,
    REG,
    Configurations,
    config_cells,
    diff_key,
    estimate_ci_cells,
    fusion_key,
    label,
    row_cell,
    value_ci_cells,
)
from traffictwin.report import model as page
from traffictwin.report.model import NA, Cell, Table, fmt_value, lookup

# the pose-error columns after the success rate: (metric key, column name)
POSE_COLUMNS = (
    ("fallback_rate", "fallback"),
    ("residual_trans_m_median", "median Δt [m]"),
    ("residual_trans_m_p90", "p90 Δt [m]"),
    ("residual_rot_deg_median", "median Δψ [deg]"),
    ("residual_rot_deg_p90", "p90 Δψ [deg]"),
)
REGISTRATION_NOTE = (
    "Error of the pose used (the estimate, or the noisy pose where the estimate was rejected: "
    "'fallback', counted in the success rate like any other pose) against the simulator's true "
    "relative pose; success = translation error <= evaluation.fusion.success_trans_m (m) and yaw "
    "error <= evaluation.fusion.success_rot_deg (deg). Wall time per pair: reports/timings/evaluate_fusion.json "
    "(this run) and benchmarks/registration.py. Δ: paired over the same pairs. " + CI_NOTE
)


def _has_success(src: page.Sources, c: str, m: str) -> bool:
    return isinstance(src.get(FUSION_FILE, fusion_key(c, m, "success_rate")), (int, float))


def _registration_row(
    src: page.Sources, configurations: Configurations, c: str, m: str
) -> list[Cell]:
    row = config_cells(configurations, c) + [Cell(label(m))]
    row += value_ci_cells(src, fusion_key(c, m, "success_rate"))  # evaluated: _has_success
    row += [row_cell(src, c, m, k) for k, _ in POSE_COLUMNS]
    dk = diff_key(c, m, REG, "success_rate")
    if isinstance(src.get(FUSION_FILE, dk), dict):
        row += estimate_ci_cells(src, dk)
    else:
        row += [Cell(NA), Cell(NA)]
    return row


def _registration_table(
    src: page.Sources, configurations: Configurations, cfgs: Sequence[str], rows: Sequence[str]
) -> Table:
    t = Table(
        "Registration: pose error of every method that estimates a pose (test split, same pairs)",
        [
            "config",
            "r [m]",
            "α [deg]",
            "method",
            "success",
            "95 % CI",
            *[name for _, name in POSE_COLUMNS],
            "Δ success vs registered",
            "95 % CI",
        ],
        note=REGISTRATION_NOTE,
        anchor="fusion-registration",
        headline=True,
    )
    for c in cfgs:
        for m in rows:
            if _has_success(src, c, m):
                t.rows.append(_registration_row(src, configurations, c, m))
    return t


def _bin_cell(src: page.Sources, axis: str, m: str, lab: str) -> Cell:
    """Success rate (n pairs) of row ``m`` in bin ``lab`` of ``axis``."""
    key = f"bins.{axis}.{m}.{lab}"
    sr = src.get(FUSION_FILE, f"{key}.success_rate")
    if not isinstance(sr, (int, float)):
        return Cell(NA)
    n = src.get(FUSION_FILE, f"{key}.n")
    count = int(n) if isinstance(n, (int, float)) else "?"
    return Cell(
        f"{fmt_value(sr, 'g4')} ({count})",
        value=[sr, n],
        derived=f"metrics/{FUSION_FILE}#{key}.success_rate (n: .n)",
    )


def _bin_table(src: page.Sources, axis: str, what: str, rows: Sequence[str]) -> Table | None:
    """Success rate per bin of the drawn ``what`` error, every configuration pooled (None
    without bins)."""
    bins = lookup(src.metrics.get(FUSION_FILE), f"bins.{axis}")
    if not isinstance(bins, dict):
        return None
    labels: list[str] = []
    for m in rows:
        for lab in bins.get(m, {}) if isinstance(bins.get(m), dict) else {}:
            if lab not in labels:
                labels.append(lab)
    if not labels:
        return None
    b = Table(
        f"Registration: success rate per bin of the drawn {what} error (all configurations pooled)",
        ["method", *[f"{lab} (n)" for lab in labels]],
        note=f"Bins of the drawn pose noise's {what} (evaluation.fusion.trans_bins_m / rot_bins_deg), "
        "as in the pose-error bins of the fusion metrics; n = pairs in the bin.",
        anchor=f"fusion-registration-{axis}-bins",
    )
    for m in rows:
        b.rows.append([Cell(label(m))] + [_bin_cell(src, axis, m, lab) for lab in labels])
    return b


def registration_tables(
    src: page.Sources, configurations: Configurations, cfgs: Sequence[str]
) -> list[Table]:
    """The registration error table (every row that estimates a pose, per configuration) and the
    success rate per bin of the drawn translation and yaw error."""
    rows = [m for m in POSE_ROWS if any(_has_success(src, c, m) for c in cfgs)]
    if not rows:
        return []
    out = [_registration_table(src, configurations, cfgs, rows)]
    for axis, what in (("translation", "translation"), ("rotation", "yaw")):
        b = _bin_table(src, axis, what, rows)
        if b is not None:
            out.append(b)
    return out
