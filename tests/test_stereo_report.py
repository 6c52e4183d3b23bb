"""The stereo section of the report: range-error, fault-detection and resolution tables from the
metrics files, every number traceable to its file, old or missing files handled."""

from __future__ import annotations

import json
from pathlib import Path

from _report_pages import page_md

from pipelines.report import providers
from tests.test_report import check_report
from traffictwin.report import render as R
from traffictwin.report.model import ReportInputs, Sources
from traffictwin.stereo import report_section as S

DISPARITY = {
    "all/bad2": 0.0216,
    "all/d1": 0.0155,
    "all/density": 0.863,
    "all/epe": 0.34,
    "fault_none/bad2": 0.0075,
    "fault_none/d1": 0.0047,
    "fault_none/density": 0.884,
    "fault_none/epe": 0.21,
    **{
        f"{g}/{b}_{m}": v
        for g in ("all", "fault_none")
        for b, base in (("z0-10m", 0.014), ("z10-30m", 0.046), ("z30-90m", 0.196))
        for m, v in (
            ("relerr_median", base),
            ("relerr_p90", 3 * base),
            ("valid_share", 0.88),
            ("gt_pixels", 1000),
        )
    },
    "fault_delay/z10-30m_relerr_p90": None,  # beyond the histogram: null
}
RULES = ("orb_paper", "orb", "valid_share", "orb_or_valid_share")
ORB = {
    "all/dropped_share": 0.059,
    **{f"rule_{r}/configured": int(r == "orb_or_valid_share") for r in RULES},
    **{
        f"rule_{r}/{k}{s}": v
        for r in RULES
        for k in ("delay_detection", "vertical_detection", "false_alarm")
        for s, v in (("", 0.5), ("_lo", 0.4), ("_hi", 0.6), ("_n", 10))
    },
    **{
        f"rule_{r}/delay_detection_v{b}{s}": v
        for r in RULES
        for b in ("0-0p5", "10-15", "0p5-5")
        for s, v in (("", 0.25), ("_lo", 0.0), ("_hi", 0.5), ("_n", 4))
    },
    "sweep/min_valid_share_0p75_false_alarm_rate": 0.0,
    "sweep/min_valid_share_0p75_delay_detection_rate": 0.58,
    "sweep/min_valid_share_0p75_vertical_detection_rate": 0.99,
    "sweep/min_valid_share_0p8_false_alarm_rate": 0.002,
    "sweep/min_valid_share_0p8_delay_detection_rate": 0.74,
    "sweep/min_valid_share_0p8_vertical_detection_rate": 0.99,
}
RESOLUTION = {
    "study/critical_lo_m": 12.0,
    "study/critical_hi_m": 21.0,
    "study/frames": 80,
    **{
        f"w{w}/{k}": v * (2 if w == 640 else 1)
        for w in (320, 640)
        for k, v in (
            ("height", 80),
            ("num_disparities", 16),
            ("gt_disparity_px_at_12m", 3.7),
            ("gt_disparity_px_at_21m", 2.1),
            ("crit_obj_relerr_median", 0.07),
            ("crit_obj_relerr_median_lo", 0.065),
            ("crit_obj_relerr_median_hi", 0.075),
            ("crit_obj_relerr_p90", 0.17),
            ("crit_obj_valid_share", 0.44),
            ("crit_all_relerr_median", 0.048),
            ("crit_all_relerr_median_lo", 0.044),
            ("crit_all_relerr_median_hi", 0.052),
            ("z0-10m_relerr_median", 0.014),
            ("z10-30m_relerr_median", 0.046),
            ("z30-90m_relerr_median", 0.16),
            ("z30-90m_relerr_p90", 0.49),
            ("sgm_ms_median", 14.0),
            ("render_ms_median", 67.0),
        )
    },
    "diff_w640_minus_w320/crit_obj_relerr_median": -0.04,
    "diff_w640_minus_w320/crit_obj_relerr_median_lo": -0.045,
    "diff_w640_minus_w320/crit_obj_relerr_median_hi": -0.035,
}


def _reports(tmp_path: Path, metrics: dict[str, dict], figures: tuple[str, ...] = ()) -> Path:
    rep = tmp_path / "reports"
    (rep / "metrics").mkdir(parents=True)
    (rep / "figures").mkdir()
    for name, data in metrics.items():
        (rep / "metrics" / name).write_text(json.dumps(data))
    for name in figures:
        (rep / "figures" / name).write_bytes(b"\x89PNG")
    return rep


def _inputs(rep: Path) -> ReportInputs:
    return ReportInputs(reports_dir=rep, profile="ci", seed=1, git_commit="c0ffee")


def _rows(table) -> list[list[str]]:
    return [[c.text for c in row] for row in table.rows]


def test_stereo_section_tables(tmp_path: Path) -> None:
    rep = _reports(
        tmp_path,
        {"disparity.json": DISPARITY, "orb.json": ORB, "stereo_resolution.json": RESOLUTION},
        ("stereo_resolution.png", "stereo_example.png"),
    )
    report = R.write_report(_inputs(rep), providers({}))
    check_report(rep, {}, {})  # every number cell equals its file's value
    sec = next(s for s in report.sections if s.title == S.TITLE)
    anchors = [t.anchor for t in sec.tables]
    assert sec.shown == 1
    assert (
        anchors
        == [  # the headline table first (the others under "More tables"), then report order
            "stereo-fault-detection",
            "stereo-accuracy",
            "stereo-range-error",
            "stereo-delay-by-speed",
            "stereo-valid-share-sweep",
            "stereo-resolution",
        ]
    )
    det, acc, rng, speed, sweep, res = sec.tables
    assert _rows(acc)[0] == ["all pairs", "2.16 %", "1.55 %", "86.30 %", "0.34"]
    assert _rows(rng)[0] == ["fault-free pairs", "0–10 m", "1,000", "88.00 %", "1.40 %", "4.20 %"]
    assert [r[0] for r in _rows(det)] == [S.RULE_LABELS[r] for r in RULES] + ["pairs evaluated"]
    assert [r[1] for r in _rows(det)] == ["", "", "", "yes", ""]  # the configured rule drops pairs
    assert _rows(det)[-1][2:] == ["10", "", "10", "", "10", ""]  # the pairs each rate is over
    assert det.rows[-1][2].src == "metrics/orb.json#rule_orb/delay_detection_n"
    assert _rows(det)[0][2:4] == ["50.00 %", "[40.00 %, 60.00 %]"]
    assert det.rows[0][3].derived.startswith("95 % cluster-bootstrap interval")
    # speed bins sorted by their lower edge, with the counts first
    assert speed.columns[1:] == ["v 0–0.5 m/s", "v 0.5–5 m/s", "v 10–15 m/s"]
    assert _rows(speed)[0] == ["delay faults (count)", "4", "4", "4"]
    assert [r[0] for r in _rows(sweep)] == ["threshold 0.75", "threshold 0.8"]
    assert res.columns == ["quantity", "width 320 px", "width 640 px"]
    rows = {r[0]: r[1:] for r in _rows(res)}
    assert rows["objects at 12–21 m: median range error"] == ["7.00 %", "14.00 %"]
    assert rows["objects at 12–21 m: median range error, 95 % CI"] == [
        "[6.50 %, 7.50 %]",
        "[13.00 %, 15.00 %]",
    ]
    # the paired difference between widths: the last rows, in the larger width's column
    assert _rows(res)[-2:] == [
        ["objects at 12–21 m: median range error, width 640 − 320 px", "", "-4.00 %"],
        [
            "objects at 12–21 m: median range error, width 640 − 320 px, 95 % CI",
            "",
            "[-4.50 %, -3.50 %]",
        ],
    ]
    assert (
        res.rows[-2][2].src
        == "metrics/stereo_resolution.json#diff_w640_minus_w320/crit_obj_relerr_median"
    )
    assert [f.path for f in sec.figures] == ["figures/stereo_resolution.png"]
    assert report.missing == []
    appendix = next(s for s in report.sections if s.title.startswith("Appendix"))
    titles = [t.title for t in appendix.tables]
    assert "reports/metrics/stereo_resolution.json" not in titles  # shown in full by the section
    assert "reports/metrics/orb.json" not in titles  # the data section shows it


def test_stereo_section_with_missing_or_old_files(tmp_path: Path) -> None:
    old = {"all/bad2": 0.071, "all/density": 0.83, "all/frames": 40}  # an older disparity.json
    rep = _reports(tmp_path, {"disparity.json": old, "orb.json": {"all/dropped_share": 0.04}})
    src = Sources(_inputs(rep))
    sec = S.section(src, [])
    assert [t.anchor for t in sec.tables] == ["stereo-accuracy"]
    assert sec.tables[0].columns == ["pairs", "bad-2 (> 2 px)", "density"]
    assert src.missing == []  # what an old file lacks is left out, not reported missing
    assert any("stereo_resolution.json` is missing" in p for p in sec.paragraphs)
    empty = S.section(Sources(_inputs(_reports(tmp_path / "e", {}))), [])
    assert empty.tables == []
    assert any("disparity.json` is missing" in p for p in empty.paragraphs)
    assert any("orb.json` is missing" in p for p in empty.paragraphs)


def _stereo_json() -> dict:
    """A stereo.json as stage stereo_learned writes it (values made up, intervals around them)."""
    out: dict = {"test/frames": 40, "test/sequences": 10}
    for source, scale in (("sgm", 1.0), ("learned", 0.5)):
        for mask in ("common", "own"):
            for _, key, _ in S.STEREO_ROWS:
                v = (0.9 if key == "density" else 0.05 if "relerr" in key else 0.3) * scale
                out[f"{source}/{mask}/{key}"] = v
                out[f"{source}/{mask}/{key}_lo"], out[f"{source}/{mask}/{key}_hi"] = (
                    v * 0.9,
                    v * 1.1,
                )
    for mask, d in (("common", -0.1), ("own", -0.2)):
        for key in ("epe", "crit_obj_relerr_median"):
            k = f"diff_learned_minus_sgm/{mask}/{key}"
            out[k], out[k + "_lo"], out[k + "_hi"] = d, d - 0.05, d + 0.05
    out["targets"] = {
        "learned_crit_obj_relerr_median": {
            "description": "learned stereo: median range error on critical-distance objects",
            "value": 0.025,
            "value_lo": 0.02,
            "value_hi": 0.03,
            "op": "<=",
            "threshold": 0.035,
            "met": True,
            "format": "pct",
        }
    }
    return out


def test_learned_stereo_tables_show_both_sources_and_their_difference(
    tmp_path: Path,
) -> None:
    """stereo.json: one table SGM | CI | learned | CI on each source's own pixels (the same pixels
    for both: every number its file's), then the paired differences on the pixels both estimate;
    its targets only as a pointer to the acceptance table; without the file the section says
    which stage has not run."""
    rep = _reports(
        tmp_path,
        {"disparity.json": DISPARITY, "orb.json": ORB, "stereo.json": _stereo_json()},
        ("stereo_learned_example.png",),
    )
    report = R.write_report(_inputs(rep), providers({}))
    check_report(rep, {}, {})
    sec = next(s for s in report.sections if s.title == S.TITLE)
    by = {t.anchor: t for t in sec.tables}
    t = by["stereo-learned"]
    rows = _rows(t)
    assert rows[0] == ["end-point error [px]", "0.300", "[0.270, 0.330]", "0.150", "[0.135, 0.165]"]
    assert t.rows[0][3].src == "metrics/stereo.json#learned/own/epe"
    assert ["density (share of GT pixels with an estimate)", "90.00 %"] == rows[3][:2]
    # the paired differences: the last rows, in the learned columns, on the common mask
    assert rows[-2] == [
        "end-point error [px] (learned − SGM)",
        "",
        "",
        "-0.100",
        "[-0.150, -0.050]",
    ]
    assert t.rows[-2][3].src == "metrics/stereo.json#diff_learned_minus_sgm/common/epe"
    assert len(rows) == len(S.STEREO_ROWS) + len(S.DIFF_ROWS)
    # the targets are judged in the acceptance table of the index: one line points there
    assert "stereo-learned-targets" not in by
    assert sum("(../README.md#acceptance-thresholds)" in p for p in sec.paragraphs) == 1
    assert any("figures/stereo_learned_example.png" in f.path for f in sec.figures)

    none = _reports(tmp_path / "none", {"disparity.json": DISPARITY, "orb.json": ORB}, ())
    report = R.write_report(_inputs(none), providers({}))
    sec = next(s for s in report.sections if s.title == S.TITLE)
    assert not any(t.anchor.startswith("stereo-learned") for t in sec.tables)
    assert any("stereo.json` is missing: stage stereo_learned" in p for p in sec.paragraphs)


def test_generalisation_tables_show_the_three_sources_and_the_paired_differences(
    tmp_path: Path,
) -> None:
    """stereo.json's ``generalisation``: SGM | full network | without the templates (each with its
    interval) on the held-out templates' frames, then the paired differences; a block without
    frames shows its reason instead of numbers."""
    g: dict = {"templates": ["roundabout", "s_curve"], "test/frames": 12, "test/sequences": 3}
    for source, v in (("sgm", 0.3), ("learned", 0.2), ("holdout", 0.25)):
        for mask in ("common", "own"):
            for _, key, _ in S.GENERALISATION_ROWS:
                g[f"{source}/{mask}/{key}"] = v
                g[f"{source}/{mask}/{key}_lo"], g[f"{source}/{mask}/{key}_hi"] = v - 0.01, v + 0.01
    for other, d in (("learned", 0.05), ("sgm", -0.05)):
        for key in ("epe", "crit_obj_relerr_median"):
            k = f"diff_holdout_minus_{other}/common/{key}"
            g[k], g[k + "_lo"], g[k + "_hi"] = d, d - 0.02, d + 0.02
    rep = _reports(
        tmp_path,
        {
            "disparity.json": DISPARITY,
            "orb.json": ORB,
            "stereo.json": {**_stereo_json(), "generalisation": g},
        },
        ("stereo_learned_example.png",),
    )
    report = R.write_report(_inputs(rep), providers({}))
    check_report(rep, {}, {})
    sec = next(s for s in report.sections if s.title == S.TITLE)
    by = {t.anchor: t for t in sec.tables}
    t = by["stereo-generalisation"]
    assert "roundabout, s_curve" in t.title and "12 frames of 3 sequences" in t.note
    assert _rows(t)[0] == [
        "end-point error [px]",
        "0.300",
        "[0.290, 0.310]",
        "0.200",
        "[0.190, 0.210]",
        "0.250",
        "[0.240, 0.260]",
    ]
    # the paired differences: the last rows, in the 'without them' columns
    diff = _rows(t)[len(S.GENERALISATION_ROWS) :]
    blank = [""] * 4
    assert diff[0] == [
        "end-point error [px] (without − full network)",
        *blank,
        "0.050",
        "[0.030, 0.070]",
    ]
    assert diff[-1] == [
        "objects at the critical distances: median range error (without − SGM)",
        *blank,
        "-5.00 %",
        "[-7.00 %, -3.00 %]",
    ]

    why = {
        "templates": ["roundabout"],
        "why": "no fault-free test frame of the held-out road templates",
    }
    rep = _reports(
        tmp_path / "why",
        {
            "disparity.json": DISPARITY,
            "orb.json": ORB,
            "stereo.json": {**_stereo_json(), "generalisation": why},
        },
        ("stereo_learned_example.png",),
    )
    sec = next(
        s for s in R.write_report(_inputs(rep), providers({})).sections if s.title == S.TITLE
    )
    rows = _rows(next(t for t in sec.tables if t.anchor == "stereo-generalisation"))
    assert rows == [["not measured", why["why"]]]


def _variants_json(chosen: str) -> dict:
    """An sgm_variants.json as the stage writes it (made-up figures)."""
    figs = {}
    for i, n in enumerate(["bs5-ur10-sw100-colour", "bs3-ur10-sw100-colour", "bs7-ur5-sw0-grey"]):
        figs[n] = {
            "settings": {"block_size": int(n[2])},
            "epe": 0.2 + 0.01 * i,
            "bad1": 0.02,
            "density": 0.9,
            "crit_obj_relerr_median": 0.07 - 0.01 * i,
            "crit_obj_relerr_p90": 0.17,
            "crit_obj_density": 0.8 - 0.1 * (i == 2),
        }
    out: dict = {
        "validation": {"frames": 160, "variants": figs},
        "choice": {
            "chosen": chosen,
            "configured": "bs5-ur10-sw100-colour",
            "is_configured": chosen == "bs5-ur10-sw100-colour",
            "rule": "lowest validation crit_obj_relerr_median among the 2 of 3 variants ...",
        },
    }
    if chosen == "bs5-ur10-sw100-colour":
        out["test"] = {"why": "the chosen variant is the configured matcher"}
        return out
    t: dict = {"test/frames": 700, "test/sequences": 100}
    for source, v in (("configured", 0.22), ("chosen", 0.21)):
        for mask in ("common", "own"):
            for _, key, _ in S.GENERALISATION_ROWS:
                t[f"{source}/{mask}/{key}"] = v
                t[f"{source}/{mask}/{key}_lo"], t[f"{source}/{mask}/{key}_hi"] = v - 0.01, v + 0.01
    for mask in ("common", "own"):
        for key in ("epe", "crit_obj_relerr_median"):
            k = f"diff_chosen_minus_configured/{mask}/{key}"
            t[k], t[k + "_lo"], t[k + "_hi"] = -0.01, -0.02, 0.0
    out["test"] = t
    return out


def test_sgm_variant_tables_show_the_configured_the_chosen_and_the_test_comparison(
    tmp_path: Path,
) -> None:
    """sgm_variants.json: the configured matcher first, the chosen one, the others by the
    criterion with the ones below the density guard marked; the test comparison when a variant
    won, only its reason when the configured matcher did; the file is not dumped again."""
    rep = _reports(
        tmp_path,
        {
            "disparity.json": DISPARITY,
            "orb.json": ORB,
            "sgm_variants.json": _variants_json("bs3-ur10-sw100-colour"),
        },
        (),
    )
    report = R.write_report(_inputs(rep), providers({}))
    check_report(rep, {}, {})
    sec = next(s for s in report.sections if s.title == S.TITLE)
    by = {t.anchor: t for t in sec.tables}
    rows = _rows(by["stereo-sgm-variants"])
    assert [r[:2] for r in rows] == [
        ["bs5-ur10-sw100-colour", "configured"],
        ["bs3-ur10-sw100-colour", "chosen"],
        ["bs7-ur5-sw0-grey", "below the density guard"],
    ]
    assert rows[0][2:] == ["0.200", "2.00 %", "90.00 %", "7.00 %", "17.00 %", "80.00 %"]
    cmp = _rows(by["stereo-sgm-chosen"])
    assert cmp[0] == ["end-point error [px]", "0.220", "[0.210, 0.230]", "0.210", "[0.200, 0.220]"]
    assert cmp[-2][3:] == ["-0.010", "[-0.020, 0.000]"]
    assert "sgm_variants.json" not in page_md(rep, "appendix").split("## Appendix")[-1]

    rep = _reports(
        tmp_path / "kept",
        {
            "disparity.json": DISPARITY,
            "orb.json": ORB,
            "sgm_variants.json": _variants_json("bs5-ur10-sw100-colour"),
        },
        (),
    )
    sec = next(
        s for s in R.write_report(_inputs(rep), providers({})).sections if s.title == S.TITLE
    )
    t = next(t for t in sec.tables if t.anchor == "stereo-sgm-variants")
    assert _rows(t)[0][:2] == ["bs5-ur10-sw100-colour", "configured and chosen"]
    assert "the chosen variant is the configured matcher" in t.note
    assert "stereo-sgm-chosen" not in {t.anchor for t in sec.tables}
