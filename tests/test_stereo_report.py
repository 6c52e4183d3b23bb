"""The stereo section of the report: the fault-detection and learned-stereo tables from the
metrics files, every number traceable to its file, old or missing files handled, the other
stereo files in the appendix."""

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
        {
            "disparity.json": DISPARITY,
            "orb.json": ORB,
            "stereo_resolution.json": RESOLUTION,
            "sgm_variants.json": {"validation": {"frames": 160}, "choice": {"chosen": "bs3"}},
        },
        ("stereo_resolution.png", "stereo_example.png"),
    )
    report = R.write_report(_inputs(rep), providers({}))
    check_report(rep, {}, {})  # every number cell equals its file's value
    sec = next(s for s in report.sections if s.title == S.TITLE)
    assert sec.shown == 1
    assert [t.anchor for t in sec.tables] == ["stereo-fault-detection"]
    (det,) = sec.tables
    assert [r[0] for r in _rows(det)] == [S.RULE_LABELS[r] for r in RULES] + ["pairs evaluated"]
    assert [r[1] for r in _rows(det)] == ["", "", "", "yes", ""]  # the configured rule drops pairs
    assert _rows(det)[-1][2:] == ["10", "", "10", "", "10", ""]  # the pairs each rate is over
    assert det.rows[-1][2].src == "metrics/orb.json#rule_orb/delay_detection_n"
    assert _rows(det)[0][2:4] == ["50.00 %", "[40.00 %, 60.00 %]"]
    assert det.rows[0][3].derived.startswith("95 % cluster-bootstrap interval")
    assert [f.path for f in sec.figures] == ["figures/stereo_resolution.png"]
    assert report.missing == []
    appendix = next(s for s in report.sections if s.title.startswith("Appendix"))
    titles = [t.title for t in appendix.tables]
    # the resolution study: its figure here, its numbers in the appendix
    assert "reports/metrics/stereo_resolution.json" in titles
    assert "| validation.frames | 160 |" in page_md(rep, "appendix")  # sgm_variants.json
    assert "reports/metrics/orb.json" not in titles  # in the appendix under its data title


def test_stereo_section_with_missing_or_old_files(tmp_path: Path) -> None:
    old = {"all/dropped_share": 0.04}  # an older orb.json, without the rules
    rep = _reports(tmp_path, {"disparity.json": DISPARITY, "orb.json": old})
    src = Sources(_inputs(rep))
    sec = S.section(src, [])
    assert sec.tables == []
    assert src.missing == []  # what an old file lacks is left out, not reported missing
    assert any("stereo.json` is missing" in p for p in sec.paragraphs)
    empty = S.section(Sources(_inputs(_reports(tmp_path / "e", {}))), [])
    assert empty.tables == []
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
