"""The report assembles what the problems' section providers give it: figures by provider, the
appendix from their declarations, findings through explicit functions, and a
new problem is one more provider."""

from __future__ import annotations

import ast
import json
from pathlib import Path

import pytest
from _report_pages import page_md

from pipelines.report import providers
from traffictwin.config import ConfigError, typed
from traffictwin.fusion import report_section as fusion_report
from traffictwin.fusion.findings import fusion_findings
from traffictwin.report import render as R
from traffictwin.report.config import ReportParams
from traffictwin.report.model import DataFile, Figure, ReportInputs, Section, SectionProvider
from traffictwin.report.tables import findings_group, markdown_bullets
from traffictwin.risk import report_section as risk_report
from traffictwin.stereo import report_section as stereo_report
from traffictwin.twin import report_section as twin_report

SRC = Path(__file__).resolve().parents[1] / "src" / "traffictwin"


def _reports(tmp_path: Path, metrics: dict[str, object], figures: list[str] = ()) -> Path:
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


def _section(report, title: str) -> Section:
    return next(s for s in report.sections if s.title == title)


def test_collect_figures_known_first_then_by_name(tmp_path: Path) -> None:
    rep = _reports(
        tmp_path,
        {},
        [
            "risk_examples.png",
            "fusion_kld_boxplot.png",
            "fusion_data_samples.png",
            "stereo_extra.png",
            "pose_extra.png",
            "twin_timeline.png",
            "misc.png",
        ],
    )
    (rep / "figures" / "notes.txt").write_text("not an image")
    (figs_fusion, figs_risk, figs_stereo, figs_twin), other = R.collect_figures(rep, providers({}))
    # known figures in the provider's order with its caption, then the others its pattern claims
    assert [(f.path, f.caption) for f in figs_fusion] == [
        (
            "figures/fusion_data_samples.png",
            f"{fusion_report.FIGURES['fusion_data_samples']} — `figures/fusion_data_samples.png`",
        ),
        (
            "figures/fusion_kld_boxplot.png",
            f"{fusion_report.FIGURES['fusion_kld_boxplot']} — `figures/fusion_kld_boxplot.png`",
        ),
        ("figures/pose_extra.png", "`figures/pose_extra.png`"),
    ]
    assert [f.path for f in figs_risk] == ["figures/risk_examples.png", "figures/stereo_extra.png"]
    assert figs_stereo == []  # the stereo section claims only its own figure (stereo_resolution)
    assert [f.path for f in figs_twin] == ["figures/twin_timeline.png"]
    assert other == [Figure("figures/misc.png", "`figures/misc.png`")]


def test_a_new_problem_is_one_more_provider(tmp_path: Path) -> None:
    """One more provider (a problem beyond the four) gets its section (after the others), its
    figures, its data file first in the appendix and keeps the files it shows out of it."""
    seen: dict[str, object] = {}

    def fleet_section(src, figures: list[Figure]) -> Section:
        seen["figures"] = [f.path for f in figures]
        sec = Section("Fleet")
        sec.paragraphs.append(f"{src.get('fleet_run_1.json', 'n')} vehicles")
        sec.figures = figures
        return sec

    fleet = SectionProvider(
        section=fleet_section,
        figures={"fleet_map": "The fleet's map"},
        figure_pattern="fleet",
        data_files=(
            DataFile("fleet_data.json", "Fleet data"),
            DataFile("fleet_more.json", "More fleet data", required=True),
        ),
        shown_files=r"fleet_run_\d+\.json",
    )
    rep = _reports(
        tmp_path,
        {
            "fleet_run_1.json": {"n": 3},
            "fleet_data.json": {"all/frames": 5},
            "other.json": {"x": 1},
        },
        ["fleet_map.png", "fleet_other.png"],
    )
    report = R.write_report(_inputs(rep), [*providers({}), fleet])
    titles = [s.title for s in report.sections]
    assert titles == [
        R.VERDICTS_TITLE,
        "Headline results",
        "Acceptance thresholds",  # the index's last section
        fusion_report.TITLE,
        risk_report.TITLE,
        stereo_report.TITLE,
        twin_report.TITLE,
        "Fleet",
        "This run: parameters, machine",
        "Appendix — every metrics file",
    ]
    assert seen["figures"] == ["figures/fleet_map.png", "figures/fleet_other.png"]
    assert _section(report, "Fleet").paragraphs == ["3 vehicles"]
    appendix = _section(report, "Appendix — every metrics file")
    # the provider's data files first, under their titles; a required one that is missing said so
    assert [t.title for t in appendix.tables] == ["Fleet data", "reports/metrics/other.json"]
    assert [[c.text for c in row] for row in appendix.tables[0].rows] == [["all/frames", "5"]]
    assert "`reports/metrics/fleet_more.json` is missing." in appendix.paragraphs
    assert _section(report, "Fleet").page == "fleet"  # a provider's page is its name
    md = page_md(rep, "fleet")
    assert "## Fleet" in md and "(../figures/fleet_map.png)" in md
    assert "## Fleet" not in (rep / "README.md").read_text()  # the index only links it


def test_fusion_section_missing_evaluation(tmp_path: Path) -> None:
    """'fusion.json is missing' is said when it is, whether or not the training files are there
    (those: the appendix)."""
    only_training = _reports(tmp_path / "a", {"train_fusion_A.json": {"val/loss": 0.5}})
    report = R.build_report(_inputs(only_training), providers({}))
    sec = _section(report, fusion_report.TITLE)
    assert any("`reports/metrics/fusion.json` is missing" in p for p in sec.paragraphs)
    assert sec.tables == []
    appendix = _section(report, "Appendix — every metrics file")
    assert [t.title for t in appendix.tables] == ["reports/metrics/train_fusion_A.json"]
    assert sec.bullet_groups[0] == (
        "Findings of this run",
        ["(no fusion.json: findings need the evaluation metrics)"],
    )

    metrics = {
        "test": {"A": {"dnn": {"kld_fou_mean": 0.25}, "naive": {"kld_fou_mean": 0.5}}},
        "diff": {
            "A": {
                "dnn": {"vs_naive": {"kld_fou_mean": {"estimate": -0.25, "lo": -0.3, "hi": -0.2}}}
            }
        },
    }
    only_eval = _reports(tmp_path / "b", {"fusion.json": metrics})
    report = R.build_report(_inputs(only_eval), providers({"A": (0.0, 0.0)}))
    sec = _section(report, fusion_report.TITLE)
    assert not any("is missing" in p for p in sec.paragraphs)
    kld = next(t for t in sec.tables if t.anchor == "fusion-kld")
    assert [c.text for c in kld.rows[0]] == ["A", "0", "0", "0.25", "0.5"]
    # network − naive: the paired-difference table, with its verdict
    diff = next(t for t in sec.tables if t.anchor == "fusion-diff")
    assert [c.text for c in diff.rows[0][:6]] == [
        "A",
        "network",
        "naive",
        "-0.25",
        "[-0.3, -0.2]",
        "lower",
    ]
    assert diff.rows[0][4].derived.endswith("fusion.json#diff.A.dnn.vs_naive.kld_fou_mean")
    # an interval containing 0 is no finding
    wide = json.loads(json.dumps(metrics))
    wide["diff"]["A"]["dnn"]["vs_naive"]["kld_fou_mean"]["hi"] = 0.01
    again = _reports(tmp_path / "c", {"fusion.json": wide})
    sec2 = _section(
        R.build_report(_inputs(again), providers({"A": (0.0, 0.0)})), fusion_report.TITLE
    )
    diff2 = next(t for t in sec2.tables if t.anchor == "fusion-diff")
    assert diff2.rows[0][5].text == "no difference shown"
    # registered − naive and naive − registered: one row (the same numbers, signs turned)
    both = json.loads(json.dumps(metrics))
    d = {"kld_fou_mean": {"estimate": -0.1, "lo": -0.2, "hi": -0.05}}
    both["test"]["A"]["registered"] = {"kld_fou_mean": 0.4}
    both["diff"]["A"]["registered"] = {"vs_naive": d}
    both["diff"]["A"]["naive"] = {"vs_registered": {"kld_fou_mean": {"estimate": 0.1}}}
    sec3 = _section(
        R.build_report(_inputs(_reports(tmp_path / "d", {"fusion.json": both})), providers({})),
        fusion_report.TITLE,
    )
    diff3 = next(t for t in sec3.tables if t.anchor == "fusion-diff")
    pairs = [(r[1].text, r[2].text) for r in diff3.rows]
    assert ("naive (noisy pose + Dempster)", "registered") not in pairs
    assert pairs.count(("registered (FM + ECC) + Dempster", "naive")) == 1
    assert kld.rows[0][1].src == "params#configurations.A.r"
    # findings come from fusion.findings, as bullets
    assert sec.bullet_groups[0] == (
        "Findings of this run",
        markdown_bullets(fusion_findings(metrics)),
    )
    assert sec.bullet_groups[0][1]
    # the headline tables: only what the sections mark, and the acceptance table last
    assert [t.anchor for t in R.results_tables(report)] == ["fusion-kld", "acceptance"]


def test_headline_tables_in_section_order(tmp_path: Path) -> None:
    risk = {
        "main_variant": "v",
        "models": {"v": {"test/mse": 0.02}},
        "baselines": {},
    }
    metrics = {"test": {"A": {"dnn": {"kld_fou_mean": 0.25}}}}
    rep = _reports(tmp_path, {"fusion.json": metrics, "risk.json": risk})
    report = R.build_report(_inputs(rep), providers({}))
    assert [t.anchor for t in R.results_tables(report)] == [
        "fusion-kld",
        "risk-results",
        "risk-confusion",
        "acceptance",  # last, as on the index
    ]
    res = R.render_results_markdown(report)
    assert res.index("Fusion: KLD(b) mean") < res.index("Risk: test results")
    assert res.endswith("Full report: [README.md](README.md).\n")


def test_findings_group_turns_markdown_into_bullets(tmp_path: Path) -> None:
    rep = _reports(tmp_path, {"x.json": {"a": 1}})
    src = R.Sources(_inputs(rep))
    got: list[object] = []

    def findings(metrics):
        got.append(metrics)
        return "## Heading\n\n| a | b |\n- first\n  continued\n* second\nplain line\n"

    assert findings_group(src, "x.json", findings) == (
        "Findings of this run",
        ["first continued", "second", "plain line"],
    )
    assert got == [{"a": 1}]
    assert findings_group(src, "y.json", findings) == (
        "Findings of this run",
        ["(no y.json: findings need the evaluation metrics)"],
    )


@pytest.mark.parametrize(
    ("href", "html_href"),
    [
        ("risk.md", "risk.html"),
        ("pages/twin.md#hazards", "pages/twin.html#hazards"),
        ("../README.md#acceptance", "../index.html#acceptance"),
        ("../figures/risk_roc.png", "../figures/risk_roc.png"),
        ("https://example.org/a.md", "https://example.org/a.md"),
        ("#acceptance", "#acceptance"),
    ],
)
def test_html_links_to_report_pages_point_at_their_html(href: str, html_href: str) -> None:
    assert R._html_href(href) == html_href
    page = R.html_page(f"see [it]({href})\n", "t", "")
    assert f'<p>see <a href="{html_href}">it</a></p>' in page


def test_report_params_schema() -> None:
    good = {
        "seed": 3,
        "profile": {"name": "ci"},
        "configurations": {"A": {"r": 0, "alpha": 0}, "B": {"r": 1.0, "alpha": 10}},
    }
    p = typed(good, ReportParams)
    assert p.seed == 3 and p.profile.name == "ci"
    assert p.pose_noise == {"A": (0.0, 0.0), "B": (1.0, 10.0)}
    for bad, key in (
        ({**good, "seed": -1}, "'seed' must be >= 0"),
        ({**good, "configurations": {"A": {"r": -1.0, "alpha": 0}}}, "'configurations.A.r'"),
        ({**good, "configurations": {"A": {"r": 1.0}}}, "'configurations.A.alpha'"),
        ({**good, "profile": {}}, "'profile.name'"),
    ):
        with pytest.raises(ConfigError, match=key):
            typed(bad, ReportParams)


def test_report_package_knows_no_problem_and_no_repo_layout() -> None:
    """report/ is the page kit: it imports neither a problem nor the workflow layer, loads no
    params and spells no project path; the problems' sections import it (one-way)."""
    for path in sorted((SRC / "report").glob("*.py")):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module:
                mods = [node.module]
                assert not {a.name for a in node.names} & {"load_params", "compose_config"}
            elif isinstance(node, ast.Import):
                mods = [a.name for a in node.names]
            elif isinstance(node, ast.Constant) and isinstance(node.value, str):
                assert node.value not in ("params.yaml", "dvc.yaml", "conf", "reports"), path.name
                continue
            else:
                continue
            for mod in mods:
                assert not mod.startswith(
                    ("traffictwin.fusion", "traffictwin.risk", "pipelines", "importlib")
                ), (path.name, mod)


def test_registration_table_shows_every_pose_estimating_row(tmp_path: Path) -> None:
    from traffictwin.fusion.report_section.tables import fusion_tables

    def row(success: float, p90: float) -> dict:
        return {
            "success_rate": success,
            "success_rate_ci": {"lo": success - 0.05, "hi": success + 0.03},
            "fallback_rate": 0.1,
            "residual_trans_m_median": 0.2,
            "residual_trans_m_p90": p90,
            "residual_rot_deg_median": 0.3,
            "residual_rot_deg_p90": 0.9,
        }

    metrics = {
        "test": {
            "D": {
                "registered": row(0.82, 0.6),
                "learned": row(0.94, 0.3),
                "naive": {"kld_fou_mean": 0.3},
            }
        },
        "diff": {
            "D": {
                "learned": {
                    "vs_registered": {
                        "success_rate": {"estimate": 0.12, "lo": 0.05, "hi": 0.19, "n_pairs": 200}
                    }
                }
            }
        },
    }
    rep = _reports(tmp_path, {"fusion.json": metrics})
    tables = fusion_tables(R.Sources(_inputs(rep)), {"D": (5.0, 20.0)})
    table = next(t for t in tables if t.anchor == "fusion-registration")
    assert table.headline
    texts = [[c.text for c in r] for r in table.rows]
    assert [t[:2] for t in texts] == [
        ["D", "registered (FM + ECC) + Dempster"],
        ["D", "learned registration + Dempster"],
    ]
    learned = texts[1]
    assert learned[2:4] == ["0.94", "[0.89, 0.97]"] and learned[5] == "0.2" and learned[6] == "0.3"
    assert learned[-2:] == ["0.12", "[0.05, 0.19]"] and texts[0][-2:] == ["n/a", "n/a"]
    # no row that estimates a pose: no table
    rep = _reports(tmp_path / "x", {"fusion.json": {"test": {"D": {"naive": {"n": 1}}}}})
    tables = fusion_tables(R.Sources(_inputs(rep)), {})
    assert "fusion-registration" not in [t.anchor for t in tables]


def _one_vs_own(prefix_rows: dict) -> dict:
    ci = {"lo": 0.01, "hi": 0.03}
    return {
        "test": {
            "D": {
                "dnn": {"kld_fou_mean": 0.02, "kld_fou_mean_ci": ci},
                "dnn[per-config]": {"kld_fou_mean": 0.025, "kld_fou_mean_ci": ci},
            }
        },
        "diff": {
            "D": {
                "dnn": {
                    "vs_dnn[per-config]": {
                        "kld_fou_mean": {"estimate": -0.005, "lo": -0.008, "hi": -0.002}
                    }
                }
            }
        },
        **prefix_rows,
    }


def test_one_network_vs_per_configuration_table_from_the_run_or_the_ablation(tmp_path: Path):
    """The comparison with the per-configuration networks shows this run's numbers when it has
    them, else the ablation experiment's collected results (reports/ablations/<name>.json)."""
    from traffictwin.fusion.report_section.tables import per_config_table

    rep = _reports(tmp_path / "run", {"fusion.json": _one_vs_own({})})
    t = per_config_table(R.Sources(_inputs(rep)), ["D"])
    texts = [[c.text for c in r] for r in t.rows]
    assert texts == [
        [
            "D",
            "0.02",
            "[0.01, 0.03]",
            "0.025",
            "[0.01, 0.03]",
            "-0.005",
            "[-0.008, -0.002]",
        ]
    ]
    assert "this run" in t.note
    # no per-config rows in this run: the ablation's file, its cells pointing there
    rep = _reports(tmp_path / "abl", {"fusion.json": {"test": {"D": {"dnn": {}}}}})
    (rep / "ablations").mkdir()
    (rep / "ablations" / "fusion.json").write_text(
        json.dumps(
            {"experiment": "ablation-fusion", "commit": "abcdef123", "fusion": _one_vs_own({})}
        )
    )
    src = R.Sources(_inputs(rep))
    t = per_config_table(src, ["D"])
    assert (
        t.rows[0][1].text == "0.02"
        and t.rows[0][1].src == "ablations/fusion.json#fusion.test.D.dnn.kld_fou_mean"
    )
    assert t.rows[0][-1].derived.endswith(
        "ablations/fusion.json#fusion.diff.D.dnn.vs_dnn[per-config].kld_fou_mean"
    )
    assert "`reports/ablations/fusion.json`" in t.note
    # neither: no table
    rep = _reports(tmp_path / "none", {"fusion.json": {"test": {"D": {"dnn": {}}}}})
    assert per_config_table(R.Sources(_inputs(rep)), ["D"]) is None


def test_targets_this_run_cannot_evaluate_come_from_the_ablation(tmp_path: Path) -> None:
    """A target 'not evaluated' in this run (one_vs_per_config needs the per-configuration
    networks) shows the ablation experiment's verdict in the acceptance table, marked as such,
    its cell pointing at the ablation's file; the appendix links the ablation's file instead of
    dumping it."""
    from traffictwin.report.acceptance import acceptance_rows
    from traffictwin.report.render import appendix_section

    def targets(entry: dict) -> dict:
        return {
            "one_vs_per_config": {"op": "<=", "threshold": 0.005, "per_config": {"D": entry}},
        }

    run = {"test": {"D": {"dnn": {}}}, "targets": targets({"status": "not evaluated"})}
    rep = _reports(tmp_path / "run", {"fusion.json": run})
    (row,) = [r for r in acceptance_rows(R.Sources(_inputs(rep)), {}) if r.problem == "fusion"]
    cells = [c.text for c in row.cells()]
    assert cells[1] == "one_vs_per_config (D)" and cells[3:] == ["<= 0.005", "n/a", "not evaluated"]
    (rep / "ablations").mkdir()
    verdict = {"value": 0.0077, "lo": 0.0051, "hi": 0.0077, "status": "fail"}
    verdict["ci_beyond_threshold"] = True
    (rep / "ablations" / "per_config.json").write_text(
        json.dumps(
            {
                "name": "per_config",
                "experiment": "ablation-per_config",
                "commit": "abcdef123",
                "fusion": {"targets": targets(verdict)},
            }
        )
    )
    src = R.Sources(_inputs(rep))
    (row,) = [r for r in acceptance_rows(src, {}) if r.problem == "fusion"]
    assert [c.text for c in row.cells()][4:] == [
        "0.0077 [0.0051, 0.0077]",
        "fail (ablation per_config)",
    ]
    assert row.value.derived.endswith(
        "ablations/per_config.json#fusion.targets.one_vs_per_config.per_config.D.value"
    )
    appendix = appendix_section(src, [], [])
    assert not any("per_config" in tb.title for tb in appendix.tables)
    assert any(
        "reports/ablations/per_config.json" in p and "abcdef12" in p for p in appendix.paragraphs
    )


def test_spec_table_hand_case(tmp_path: Path) -> None:
    """The fusion tables' generic builder: label cells, then one cell per ``(header, key)`` with
    the row's names filled in; ``_ci`` an interval, ``_verdict`` the interval rule, a paired
    difference's estimate; n/a where the row or difference was not evaluated."""
    from traffictwin.fusion.report_section.tables import D, T, spec_table, with_ci

    metrics = {
        "test": {"A": {"dnn": {"kld_fou_mean": 0.15, "kld_fou_mean_ci": {"lo": 0.1, "hi": 0.2}}}},
        "diff": {
            "A": {"dnn": {"vs_naive": {"kld_fou_mean": {"estimate": -0.1, "lo": -0.2, "hi": 0.05}}}}
        },
    }
    src = R.Sources(_inputs(_reports(tmp_path, {"fusion.json": metrics})))
    assert with_ci("KLD(b)", "k") == [("KLD(b)", "k"), ("95 % CI", "k_ci")]
    rows = [([c], {"c": c, "m": "dnn"}) for c in ("A", "B")]
    t = spec_table(src, rows, with_ci("KLD(b)", f"{T}kld_fou_mean"), ("config",), title="t")
    assert t.columns == ["config", "KLD(b)", "95 % CI"]
    assert [[getattr(c, "text", c) for c in r] for r in t.rows] == [
        ["A", "0.15", "[0.1, 0.2]"],
        ["B", "n/a", "n/a"],
    ]
    assert t.rows[0][1].src == "metrics/fusion.json#test.A.dnn.kld_fou_mean"
    d = spec_table(
        src,
        [([b], {"c": "A", "m": "dnn", "b": b}) for b in ("naive", "registered")],
        [*with_ci("Δ", f"{D}kld_fou_mean"), ("verdict", f"{D}kld_fou_mean_verdict")],
        ("baseline",),
        title="d",
    )
    assert [[getattr(c, "text", c) for c in r] for r in d.rows] == [
        ["naive", "-0.1", "[-0.2, 0.05]", "no difference shown"],
        ["registered", "n/a", "n/a", "n/a"],
    ]
    assert d.rows[0][1].src == "metrics/fusion.json#diff.A.dnn.vs_naive.kld_fou_mean.estimate"
    assert src.missing == []


def test_spec_columns_and_cells_by_hand(tmp_path: Path) -> None:
    """The spec-driven table builder of the risk and twin sections: a column per spec, a "95 % CI"
    column after those with an interval; the cells of one row read ``<base>.<key>`` and
    ``<key>_ci``, a dashed key shows "—" in both."""
    from traffictwin.report.model import Sources
    from traffictwin.risk.report_tables import spec_cells, spec_columns

    specs = (("share", "a", "pct", True), ("count", "n", "int", False), ("lead", "b", "f2", True))
    assert spec_columns(specs[:1], specs[1:]) == ["share", "95 % CI", "count", "lead", "95 % CI"]
    row = {"a": 0.25, "a_ci": [0.2, 0.3], "n": 1234, "b": 1.5, "b_ci": {"lo": 1.0, "hi": 2.0}}
    src = Sources(_inputs(_reports(tmp_path, {"x.json": {"r": row}})))
    cells = spec_cells(src, "x.json", "r", specs)
    assert [c.text for c in cells] == [
        "25.00 %",
        "[20.00 %, 30.00 %]",
        "1,234",
        "1.50",
        "[1.00, 2.00]",
    ]
    assert cells[0].src == "metrics/x.json#r.a" and cells[1].value == [0.2, 0.3]
    dashed = spec_cells(src, "x.json", "r", specs, dash=("a",))
    assert [c.text for c in dashed][:3] == ["—", "—", "1,234"]
    assert [c.text for c in spec_cells(src, "x.json", "gone", specs[1:2])] == ["n/a"]
    assert src.missing == ["metrics/x.json#gone.n"]
