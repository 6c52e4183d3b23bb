"""The report: every number traced to its file, well-formed HTML, figures present.

Unit tests render small synthetic metrics files (fast, no DAG); the slow test checks the
report the ci DAG produced (`ci_dag`).
"""

from __future__ import annotations

import functools
import json
import math
import re
import struct
import xml.etree.ElementTree as ET
import zlib
from html.parser import HTMLParser
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from _report_pages import all_html, all_md, broken_links, page_files, page_html, page_md

from pipelines.report import providers
from traffictwin import paper_numbers as P
from traffictwin.report import model as M
from traffictwin.report import render as R
from traffictwin.report.claims import VERDICTS

NUM_RE = re.compile(r"^-?[\d,]*\.?\d+(e[+-]?\d+)?( %)?$|^\d+:\d\d(:\d\d)?$")


# --------------------------------------------------------------------------- parsing helpers
class _Tables(HTMLParser):
    """Collects tables as rows of (text, attrs) cells, and every <img>."""

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.tables: list[list[list[tuple[str, dict[str, str]]]]] = []
        self.imgs: list[dict[str, str]] = []
        self._cell: list[str] | None = None
        self._attrs: dict[str, str] = {}
        self._in_body = False

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = {k: v or "" for k, v in attrs}
        if tag == "table":
            self.tables.append([])
        elif tag == "tbody":
            self._in_body = True
        elif tag == "tr" and self._in_body:
            self.tables[-1].append([])
        elif tag == "td":
            self._cell, self._attrs = [], a
        elif tag == "img":
            self.imgs.append(a)

    def handle_endtag(self, tag: str) -> None:
        if tag == "td" and self._cell is not None:
            self.tables[-1][-1].append(("".join(self._cell), self._attrs))
            self._cell = None
        elif tag == "tbody":
            self._in_body = False

    def handle_data(self, data: str) -> None:
        if self._cell is not None:
            self._cell.append(data)


def md_tables(md: str) -> list[list[list[str]]]:
    """Body rows of every markdown table (header and separator dropped), cells unescaped, inline code stripped."""
    tables, cur = [], None
    for line in md.splitlines():
        if line.startswith("|"):
            if cur is None:
                cur = []
                tables.append(cur)
            cells = [
                c.strip().replace("\\|", "|") for c in re.split(r"(?<!\\)\|", line.strip())[1:-1]
            ]
            cur.append([re.sub(r"`([^`]*)`", r"\1", c) for c in cells])
        else:
            cur = None
    return [t[2:] for t in tables]


def resolve(
    src: str,
    reports: Path,
    run_params: dict[str, Any],
    configurations: dict[str, tuple[float, float]],
) -> Any:
    """The value a ``data-src`` names, read independently from its file."""
    if src.startswith("paper:"):
        ref = src.removeprefix("paper:")
        table, _, key = ref.partition(".")
        if table == "derived":
            return P.risk_confusion_derived()[key]
        if table == "FUSION_CONFIGURATIONS":
            cfg, _, which = key.partition(".")
            return P.FUSION_CONFIGURATIONS[cfg][0 if which == "r" else 1]
        return getattr(P, table)[key].value
    path, _, key = src.partition("#")
    if path == "params":
        if key.startswith("configurations."):
            _, cfg, which = key.split(".")
            return configurations[cfg][0 if which == "r" else 1]
        return run_params[key]
    file = reports / path
    stat = file.stat()
    return M.lookup(_json_file(file, stat.st_mtime_ns, stat.st_size), key, M.ABSENT)


@functools.lru_cache(maxsize=64)
def _json_file(path: Path, mtime_ns: int, size: int) -> Any:
    """A JSON file's content, read once per version (every cell of a table names the same
    file: reading it per cell took most of a whole report's check). Callers must not mutate it."""
    return json.loads(path.read_text())


def rebuilt_report(
    reports: Path,
    run_params: dict[str, Any],
    configurations: dict[str, tuple[float, float]],
    acceptance: dict[str, Any] | None = None,
) -> M.Report:
    """The report model rebuilt from the files under ``reports`` (the cells remember their
    sources); the profile and seed only change the intro, which holds no table."""
    inputs = M.ReportInputs(reports, "", 0, "", run_params, acceptance=acceptance or {})
    return R.build_report(inputs, providers(configurations))


def check_report(
    reports: Path,
    run_params: dict[str, Any],
    configurations: dict[str, tuple[float, float]],
    acceptance: dict[str, Any] | None = None,
) -> int:
    """Assert the rendered files -- the index and every page, Markdown and HTML -- agree with the
    report model rebuilt from their sources (every number cell's value its file's, its text that
    value formatted) and their links resolve; returns the number of sourced cells checked."""
    assert broken_links(reports) == []
    mds, htmls = page_files(reports), page_files(reports, html=True)
    assert [p.stem for p in mds[1:]] == [p.stem for p in htmls[1:]] and len(mds) > 1
    for md, html in zip(mds, htmls):
        check_page(reports, md.read_text(), html.read_text())
    rep = rebuilt_report(reports, run_params, configurations, acceptance)
    tables = [t for p in R.report_pages(rep) for s in p.sections for t in s.tables]
    shown = [t for p in mds for t in md_tables(p.read_text())]
    assert len(shown) == len(tables)
    checked = 0
    for t, rows in zip(tables, shown):
        assert rows == [[_md_text(c.text) for c in r] for r in t.rows], t.title
        for c in (c for r in t.rows for c in r):
            checked += check_cell(c, reports, run_params, configurations)
    return checked


def _md_text(text: str) -> str:
    """A cell's text as :func:`md_tables` reads it back from the Markdown."""
    return re.sub(r"`([^`]*)`", r"\1", text.replace("\n", " ")).strip()


def check_cell(
    c: M.Cell,
    reports: Path,
    run_params: dict[str, Any],
    configurations: dict[str, tuple[float, float]],
) -> int:
    """Assert a cell with a source shows its file's value formatted (1: checked) and that a cell
    without a source or derivation shows no number (0)."""
    if c.src is None:
        assert c.derived or not NUM_RE.match(c.text.strip()), f"number without a source: {c.text!r}"
        return 0
    want = resolve(c.src, reports, run_params, configurations)
    assert want is not M.ABSENT, c.src
    if want is None:  # JSON null in the metrics file (the writers' NaN)
        assert c.value is None and c.text == M.NA, c.src
        return 1
    assert c.value == want or (
        isinstance(want, float) and math.isnan(want) and math.isnan(c.value)
    ), c.src
    assert c.text == M.fmt_value(want, c.fmt or "g4"), (c.src, c.text)
    return 1


def check_page(reports: Path, md: str, page: str) -> None:
    """Assert one page's HTML ``page`` is well-formed and shows the tables of its Markdown ``md``,
    cell for cell, and that the images of both exist."""
    # well-formed: parses as XML once the doctype is dropped
    ET.fromstring(page.replace("<!DOCTYPE html>", "", 1))
    parser = _Tables()
    parser.feed(page)
    ht = [
        [[re.sub(r"\s+", " ", t).strip() for t, _ in row] for row in table]
        for table in parser.tables
    ]
    assert md_tables(md) == ht
    for img in parser.imgs:  # the images of the HTML: files (broken_links: relative to the page)
        assert not img["src"].startswith("data:"), img["src"][:40]
    for ref in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", md):
        assert (reports / ref.removeprefix("../")).is_file(), ref


# --------------------------------------------------------------------------- synthetic inputs
def tiny_png() -> bytes:
    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data))
            + kind
            + data
            + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
        )

    raw = b"\x00\xff\x00\x00" * 1  # one red pixel, filter byte 0
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", struct.pack(">IIBBBBB", 1, 1, 8, 2, 0, 0, 0))
        + chunk(b"IDAT", zlib.compress(raw))
        + chunk(b"IEND", b"")
    )


def fusion_metrics() -> dict:
    """Layout of evaluate_fusion's fusion.json: test[cfg][row][metric] (+ <metric>_ci {lo, hi}),
    diff[cfg][row][vs_<base>][metric], label, targets, cross[net][test cfg][metric]; a loss
    variant row dnn[paper] at D only."""
    test: dict = {}
    diff: dict = {}
    for i, c in enumerate("ABCD"):
        test[c] = {}
        rows = [("dnn", 1.0), ("naive", 3.0), ("registered", 2.0)]
        if c == "D":
            rows.append(("dnn[paper]", 1.5))
        for m, worse in rows:
            kld = 0.1 + 0.05 * i * worse + (0.02 if m == "dnn" and c == "A" else 0)
            v = {
                "kld_fo_mean": kld,
                "kld_fo_median": 0.09 + 0.01 * i,
                "kld_fou_mean": kld + 0.1,
                "kld_fo_q25": 0.05,
                "kld_fo_q75": 0.15,
                "n": 12.0,
                "u_mean": 0.25,
                "u_auroc": 0.75,
                **{
                    f"{k}_{cls}": 0.9 - 0.05 * i * worse
                    for k in ("precision", "recall", "dice")
                    for cls in ("occ", "free")
                },
            }
            for k in ("kld_fou_mean", "kld_fo_mean", "dice_occ", "dice_free", "u_mean", "u_auroc"):
                v[f"{k}_ci"] = {"lo": v[k] - 0.01, "hi": v[k] + 0.01}
            test[c][m] = v
        diff[c] = {}
        for m in test[c]:
            for b in ("naive", "registered"):
                if m != b:
                    diff[c].setdefault(m, {})[f"vs_{b}"] = {
                        k: {
                            "estimate": test[c][m][k] - test[c][b][k],
                            "lo": test[c][m][k] - test[c][b][k] - 0.005,
                            "hi": test[c][m][k] - test[c][b][k] + 0.005,
                            "n_pairs": 12,
                        }
                        for k in ("kld_fou_mean", "kld_fo_mean", "dice_occ")
                    }
    cross = {
        n: {c: {"kld_fou_mean": 0.1 + 0.01 * (ord(n) + 2 * ord(c) - 195)} for c in "ABCD"}
        for n in "ABCD"
    }
    targets = {
        "u_auroc": {
            "description": "AUROC of the network's u for wrongly classified cells",
            "threshold": 0.85,
            "op": ">=",
            "status": "fail",
            "per_config": {
                c: {
                    "value": 0.75,
                    "lo": 0.74,
                    "hi": 0.76,
                    "status": "fail",
                    "ci_beyond_threshold": True,
                }
                for c in "ABCD"
            },
        },
        "hybrid_vs_registered": {
            "description": "registered+network vs registered",
            "threshold": 0.0,
            "op": "<",
            "status": "not evaluated",
            "per_config": {
                c: {
                    "value": None,
                    "lo": None,
                    "hi": None,
                    "status": "not evaluated",
                    "why": "no row",
                }
                for c in "CD"
            },
        },
    }
    return {
        "test": test,
        "diff": diff,
        "label": {c: {"u_mean": 0.5, "u_mean_ci": {"lo": 0.45, "hi": 0.55}} for c in "ABCD"},
        "targets": targets,
        "bootstrap": {"n_boot": 2000, "seed": 0, "level": 0.95, "cluster": "scenario"},
        "cross": cross,
    }


def risk_metrics() -> dict:
    """risk.json as evaluate_risk writes it (built with the evaluation's own metric functions)."""
    from traffictwin.io.jsonio import json_clean
    from traffictwin.risk.evaluation import PAPER, evaluate

    y = np.array([0.0, 0.0, 0.05, 0.2, 0.01, 0.5, 0.0, 0.04])
    p = np.array([0.01, 0.06, 0.04, 0.1, 0.0, 0.3, 0.02, 0.0])
    base = np.full_like(y, 0.1)
    out = {
        "paper": PAPER,
        "split": "test",
        "primary_label": "risk_thw_paper",
        "thresholds_s": [1.5, 1.0],
        "n_frames": {"total": 100, "orb_outliers_dropped": 7, "train": 60, "val": 12, "test": 21},
        "models": {
            v: {
                "label": "risk_thw_paper",
                "inputs": inputs,
                "speed": False,
                "n_parameters": 250_000 + i,
                "n_train": 60,
                "steps": 12,
                "best_step": 10 - i,
                "best_val_mse": 0.02 + i / 100,
                **evaluate(y, p * (1 - i / 2), (1.5, 1.0)),
            }
            for i, (v, inputs) in enumerate((("rgbd", ["rgb", "disp_sgm"]), ("rgb", ["rgb"])))
        },
        "baselines": {
            "train_mean": {"label": "risk_thw_paper", "value": 0.1, **evaluate(y, base, (1.5, 1.0))}
        },
        "region": {
            "predictors": {
                "rgbd": {
                    "risk_thw_paper": {"test/mse": 0.01, "accuracy": 0.75},
                    "risk_thw_fov": {"test/mse": 0.005, "accuracy": 0.875},
                }
            }
        },
        "main_variant": "rgbd",
    }
    return json_clean(out)


@pytest.fixture
def reports(tmp_path: Path) -> Path:
    rep = tmp_path / "reports"
    (rep / "metrics").mkdir(parents=True)
    (rep / "figures").mkdir()
    (rep / "timings").mkdir()
    (rep / "metrics" / "fusion.json").write_text(json.dumps(fusion_metrics()))
    # NaN is what json.dumps writes for a missing precision; the report shows n/a for it
    (rep / "metrics" / "risk.json").write_text(json.dumps(risk_metrics()))
    (rep / "metrics" / "disparity.json").write_text(
        json.dumps(
            {
                "all/bad2": 0.071,
                "all/density": 0.83,
                "all/frames": 40,
                "none/bad2": 0.05,
                "delay/bad2": 0.3,
            }
        )
    )
    (rep / "metrics" / "orb.json").write_text(
        json.dumps(
            {
                "all/dropped_share": 0.042,
                "all/detection_rate": 0.9,
                "delay/detection_rate": 0.8,
                "none/false_alarm_rate": 0.01,
            }
        )
    )
    (rep / "metrics" / "train_fusion_A.json").write_text(
        json.dumps({"val/loss": 0.25, "epochs": 3})
    )
    (rep / "metrics" / "train_fusion_B.json").write_text(
        json.dumps({"val/loss": 0.5, "epochs": 4, "best_epoch": 2})
    )
    (rep / "metrics" / "extra.json").write_text(json.dumps({"a": {"b/c": 1.5}, "note": "text"}))
    (rep / "figures" / "fusion_kld_box.png").write_bytes(tiny_png())
    (rep / "figures" / "risk_training_curves.png").write_bytes(tiny_png())
    (rep / "figures" / "something_else.png").write_bytes(tiny_png())
    for stage, secs in (("generate_fusion", 12.5), ("train_fusion@A", 30.25), ("report", 1.0)):
        extra = {"run_id": "r0a", "train_seconds": 29.5} if stage == "train_fusion@A" else {}
        (rep / "timings" / f"{stage.replace('@', '-')}.json").write_text(
            json.dumps({"stage": stage, "seconds": secs, **extra})
        )
    (rep / "environment.json").write_text(
        json.dumps(
            {
                "cpu": "Test CPU",
                "cpu_count": 2,
                "memory_gb": 23.4,
                "gpu": None,
                "python": "3.11.9",
                "packages": {"torch": "2.13.0"},
            }
        )
    )
    return rep


CONFIGURATIONS = {"A": (0.0, 0.0), "B": (1.0, 10.0), "C": (2.5, 15.0), "D": (5.0, 20.0)}


def make_inputs(rep: Path) -> M.ReportInputs:
    return M.ReportInputs(
        reports_dir=rep,
        profile="ci",
        seed=7,
        git_commit="abc123",
        run_params={
            "seed": 7,
            "fusion_data.n_scenarios": 4,
            "grid.cell": 0.64,
            "trainer.accelerator": "cpu",
        },
    )


# --------------------------------------------------------------------------- unit tests
def test_fmt_value_hand_cases() -> None:
    assert M.fmt_value(0.0123456) == "0.01235"
    assert M.fmt_value(0.8125, "pct") == "81.25 %"
    assert M.fmt_value(72.87, "pct_raw") == "72.87 %"
    assert M.fmt_value(67052, "int") == "67,052"
    assert M.fmt_value(75.4, "s") == "1:15" and M.fmt_value(3725, "s") == "1:02:05"
    assert (
        M.fmt_value(30.25, "f1") == "30.2"
    )  # banker's rounding of the binary value, as Python formats it
    assert M.fmt_value(float("nan")) == "n/a" and M.fmt_value(None) == "n/a"
    assert M.fmt_value(float("inf")) == "inf" and M.fmt_value(True) == "true"
    with pytest.raises(ValueError, match="unknown format"):
        M.fmt_value(1.0, "x9")


def test_number_cell_keeps_its_source_value_and_format() -> None:
    c = M.number_cell(0.8125, "pct", "metrics/risk.json#test/acc", "why")
    assert (c.text, c.src, c.value, c.fmt, c.title) == (
        "81.25 %",
        "metrics/risk.json#test/acc",
        0.8125,
        "pct",
        "why",
    )
    assert M.number_cell(None, "g4", "metrics/x.json#k").text == "n/a"


def test_paper_numbers_consistent() -> None:
    d = P.risk_confusion_derived()
    assert d["n"] == P.RISK["n_effective"].value  # Table 1 covers the whole effective data set
    assert (
        round(d["accuracy_pct"], 2) == P.RISK["accuracy"].value
    )  # 72.87 %: the table is read the right way round
    assert P.RISK_CONFUSION["tp"].value + P.RISK_CONFUSION["fn"].value == P.RISK["n_critical"].value
    assert abs(d["orb_outlier_pct"] - P.RISK["orb_outlier_pct"].value) < 0.2
    assert set(P.FUSION_CONFIGURATIONS) == {"A", "B", "C", "D"}


def test_renderer_on_synthetic_metrics(reports: Path) -> None:
    inputs = make_inputs(reports)
    rep = R.write_report(inputs, providers(CONFIGURATIONS))
    checked = check_report(reports, dict(inputs.run_params), CONFIGURATIONS)
    # fusion: the KLD table 4 configs x (r, alpha, 3 methods) + 12 rows x (KLD(a), Dice occ, Dice
    # free, mean u) + 12 paired differences x 3 estimates + the appendix's 16 cross; risk: 5 x 2 +
    # 6 paper + 4 + 4
    assert checked >= 4 * 5 + 12 * 4 + 12 * 3 + 16 + 10 + 6 + 8
    md = all_md(reports)  # the index and every page, in reading order
    page = all_html(reports)
    # paper numbers and ours side by side, from their sources
    risk = json.loads((reports / "metrics" / "risk.json").read_text())
    main = risk["models"]["rgbd"]
    acc = main["at_1.5s"]["accuracy"]
    assert acc == 0.75  # hand count: y > 1/30 at 2, 3, 5, 7; p > 1/30 at 1, 2, 3, 5 -> 6 of 8 agree
    # the results table: the paper's row, then every predictor (no intervals in this risk.json);
    # columns: MSE, MAE, THW error, accuracy, balanced accuracy, precision, recall, ...
    results = next(t for t in md_tables(md) if t[0][0] == "paper (Feth et al.)")
    paper, rgbd = results[0], next(r for r in results if r[0] == "rgbd")
    assert paper[4] == "0.0147" and paper[7] == "72.87 %"
    assert paper[9] == "77.86 %"  # precision of 'critical': 67052 / (67052 + 19069)
    assert rgbd[1:5] == ["risk_thw_paper", "main", "n/a", M.fmt_value(main["test/mse"])]
    assert rgbd[7] == "75.00 %" and rgbd[9] == "75.00 %"  # accuracy; precision: 3 of tp + fp = 4
    cm = main["at_1.5s"]["confusion"]
    assert (cm["tp"], cm["fp"], cm["fn"], cm["tn"]) == (3, 1, 1, 3)
    assert (
        "| predicted critical | 67,052 | 63.16 % | 19,069 | 17.96 % | 3 | 37.50 % | 1 | 12.50 % |"
        in md
    )
    assert (
        "| predicted uncritical | 9,737 | 9.17 % | 10,312 | 9.71 % | 1 | 12.50 % | 3 | 37.50 % |"
        in md
    )
    assert results[1][:8] == ["Wang & Kato [20]", "—", "paper", "—", "—", "—", "—", "70.77 %"]
    # the paper's data in a sentence; this run's per split and the region check: the appendix
    assert "110,152 stereo frames, of which the ORB check drops 3,982" in md
    assert "| n_frames.orb_outliers_dropped | 7 |" in md and "| n_frames.test | 21 |" in md
    assert "| region.predictors.rgbd.risk_thw_paper.accuracy | 0.75 |" in md
    # derived ranking: our numbers say network < baseline for B, paper too
    anchors = [t.anchor for s in rep.sections for t in s.tables]
    kld = md_tables(md)[anchors.index("fusion-kld")]  # the headline: KLD(b)
    diffs = md_tables(md)[anchors.index("fusion-diff")]  # network − naive with its verdict
    vs_naive = [r[3:6] for r in diffs if r[1:3] == ["network", "naive"]]
    assert vs_naive == [["0.02", "[0.015, 0.025]", "higher"]] + [
        [
            f"{-0.1 * i:.1f}".rstrip("0"),
            f"[{-0.1 * i - 0.005:.3f}, {-0.1 * i + 0.005:.3f}]",
            "lower",
        ]
        for i in (1, 2, 3)
    ]
    # r, alpha, then dnn / naive / registered / dnn[paper] (only at D)
    assert kld[1][:7] == ["B", "1", "10", "0.25", "0.35", "0.3", "n/a"]
    assert kld[3][6] == "0.425"
    # KLD(a): the estimates table only (the paper's Fig. 5 ranking: the verdict table's claims)
    assert "fusion-kld-a" not in anchors
    # the cross table's numbers: the appendix's fusion.json
    assert "fusion-cross" not in anchors and "| cross.A.B.kld_fou_mean | 0.12 |" in md
    # the targets: the index's acceptance table (none on the fusion page)
    assert "fusion-targets" not in anchors
    index_md = (reports / "README.md").read_text()
    acceptance = [[r[0], r[1], r[3], r[4], r[5]] for r in md_tables(index_md)[-1]]
    assert ["fusion", "u_auroc (A)", ">= 0.85", "0.75 [0.74, 0.76]", "fail"] in acceptance
    assert ["fusion", "hybrid_vs_registered (D)", "< 0", "n/a", "not evaluated"] in acceptance
    # the loss variant dnn[paper]: its own rows in the estimates and difference tables
    estimates = md_tables(md)[anchors.index("fusion-ci")]
    paper = next(r for r in estimates if r[:2] == ["D", "dnn[paper]"])
    assert paper[2] == "[0.415, 0.435]" and "fusion-loss-ablation" not in anchors
    assert ["D", "dnn[paper]", "registered"] in [r[:3] for r in diffs]
    # the data differs: said plainly, on the index
    index = (reports / "README.md").read_text()
    assert "data differs from the papers'" in index and "own simulator" in index
    # no commit or wall times (they differ between identical runs: the report is a DVC output)
    # -- those are in the run records reports/timings/<stage>.json
    assert "abc123" not in md
    assert not any(t.anchor == "timings" for s in rep.sections for t in s.tables)
    assert "Stage wall times" not in md and "30.25" not in md
    assert "reports/timings/<stage>.json" in page_md(reports, "run")
    # NaN in a metrics file is shown as n/a
    assert "n/a" in md
    # figures grouped by paper, referenced as files from the HTML and the markdown of their page
    fusion = page_md(reports, "fusion")
    assert "![" in fusion and "(../figures/fusion_kld_box.png)" in fusion
    assert page.count("data:image/png;base64,") == 0
    assert page.count('src="../figures/') == 3 and "![" not in index
    # results table for the project README
    res = (reports / "results_table.md").read_text()
    assert (
        "Fusion: KLD(b) mean" in res
        and "Risk: test results" in res
        and "Risk: confusion matrix" in res
    )
    assert "Parameters of this run" not in res
    # appendix lists the other metrics files
    assert (
        "**reports/metrics/train_fusion_B.json**" in md and "| best_epoch | 2 |" in md
    )  # the trainings, one table each
    assert "| models.rgbd.n_parameters | 250,000 |" in md  # each variant's training
    assert (
        "reports/metrics/extra.json" in md and "| a.b/c | 1.5 |" in md and "| note | text |" in md
    )
    assert rep.missing == []


def test_index_holds_only_the_verdicts_the_headline_and_the_links(reports: Path) -> None:
    """The index (README.md, index.html) holds the verdict table, the headline table and the list
    of pages -- no section body; every other section lands on its own page, whole: its tables,
    figures and findings there and nowhere else."""
    rep = R.write_report(make_inputs(reports), providers(CONFIGURATIONS))
    index, html = (reports / "README.md").read_text(), (reports / "index.html").read_text()
    heads = re.findall(r"^## (.+)$", index, flags=re.M)
    assert heads == [R.VERDICTS_TITLE, "Headline results", "Acceptance thresholds", "Pages"]
    assert [t.anchor for s in rep.sections if not s.page for t in s.tables] == [
        "verdicts",
        "headline",
        "acceptance",  # the index's last table: every target's verdict
    ]
    assert "![" not in index and "<details" not in index and "### " not in index
    assert html.count("<table>") == 3  # the same three tables
    assert "<img" not in html and "<details" not in html
    # the verdict table within the first 40 lines, every claim with a computed verdict
    first = "\n".join(index.splitlines()[:40])
    verdicts = md_tables(first)[0]
    assert len(verdicts) == len(P.FUSION_CLAIMS) + 4  # fusion's claims, the risk paper's four
    assert {r[-1] for r in verdicts} <= set(VERDICTS)
    # the list of pages: one per section with a page, in reading order, each page there
    pages = [p.stem for p in page_files(reports)[1:]]
    assert pages == list(dict.fromkeys(s.page for s in rep.sections if s.page))
    assert pages == ["fusion", "risk", "stereo", "twin", "run", "appendix"]
    for sec in rep.sections:
        if not sec.page:
            continue
        md = page_md(reports, sec.page)
        assert f"## {sec.title}\n" in md, sec.title
        assert f"## {sec.title}\n" not in index
        for t in sec.tables:
            assert f"**{t.title}**" in md and f"**{t.title}**" not in index, t.title
        for f in sec.figures:
            assert f"](../{f.path})" in md, f.path
        for head, _ in sec.bullet_groups:
            assert f"### {head}\n" in md, head
        others = [p for p in pages if p != sec.page]  # each section on exactly one page
        assert all(f"## {sec.title}\n" not in page_md(reports, o) for o in others), sec.title
    # the smaller index: no page inlines an image or the style sheet; every page links the one
    # style sheet reports/style.css (index: style.css, a page: ../style.css), written verbatim
    assert all("data:image" not in p.read_text() for p in page_files(reports, html=True))
    assert all("<style" not in p.read_text() for p in page_files(reports, html=True))
    assert '<link rel="stylesheet" href="style.css"/>' in html
    assert '<link rel="stylesheet" href="../style.css"/>' in page_html(reports, "fusion")
    css = (reports / R.STYLE).read_text()
    assert css == R.CSS and "details>summary{cursor:pointer}" in css and "&gt;" not in css


def test_link_checker_finds_a_broken_link_and_a_missing_anchor(reports: Path) -> None:
    """Every relative link and image of every page resolves (file, and anchor on the target
    page); the checker names a missing figure, a missing page and an anchor not on its page."""
    R.write_report(make_inputs(reports), providers(CONFIGURATIONS))
    assert broken_links(reports) == []
    fusion = reports / R.PAGES / "fusion.md"
    text = fusion.read_text()
    assert "(../figures/fusion_kld_box.png)" in text and "](risk.md)" in text
    fusion.write_text(text + "\n[x](risk.md#no-such-heading)\n")
    (reports / "figures" / "fusion_kld_box.png").unlink()
    (reports / R.PAGES / "run.html").unlink()
    bad = broken_links(reports)
    assert any(b.startswith("pages/fusion.md: ../figures/fusion_kld_box.png") for b in bad), bad
    assert any(b.startswith("pages/fusion.html: ../figures/fusion_kld_box.png") for b in bad), bad
    assert "pages/fusion.md: risk.md#no-such-heading (no anchor #no-such-heading)" in bad
    assert any(b.startswith("index.html: pages/run.html (no file") for b in bad), bad
    # an anchor present on the target page passes: the twin section's heading
    ok = R._slug("Cooperative twin — risk from N vehicles' fused maps")
    fusion.write_text(text + f"\n[y](twin.md#{ok})\n")
    assert not any("twin.md#" in b for b in broken_links(reports))


def test_link_checker_finds_a_missing_or_wrong_style_sheet(reports: Path) -> None:
    """Every HTML page links the one style sheet reports/style.css by its path from the page's
    folder; the checker names a missing style.css, a page that links another path (resolving or
    not), a page without the link and a page that inlines its style again."""
    R.write_report(make_inputs(reports), providers(CONFIGURATIONS))
    assert broken_links(reports) == []
    link = '<link rel="stylesheet" href="../style.css"/>'
    risk, twin, run = (reports / R.PAGES / f"{n}.html" for n in ("risk", "twin", "run"))
    (reports / "pages" / "style.css").write_text(R.CSS)  # resolves, but is not the report's
    risk.write_text(risk.read_text().replace(link, '<link rel="stylesheet" href="style.css"/>'))
    twin.write_text(twin.read_text().replace(link, ""))
    run.write_text(run.read_text().replace(link, link + "<style>body{}</style>"))
    (reports / R.STYLE).unlink()
    bad = broken_links(reports)
    assert any(b.startswith("index.html: style.css (no file") for b in bad), bad
    assert any(b.startswith("pages/fusion.html: ../style.css (no file") for b in bad), bad
    assert "pages/risk.html: style.css (style sheet is not reports/style.css)" in bad
    assert "pages/twin.html: 0 style sheet links (want one, to style.css)" in bad
    assert "pages/run.html: an inline <style> (the style sheet is style.css)" in bad
    (reports / R.STYLE).write_text(R.CSS)  # back: only the three edited pages are named
    assert sorted({b.split(":")[0] for b in broken_links(reports)}) == [
        "pages/risk.html",
        "pages/run.html",
        "pages/twin.html",
    ]


def test_a_page_left_from_an_earlier_rendering_is_removed(reports: Path) -> None:
    """reports/pages is the stage's output: a page no section renders any more goes."""
    (reports / R.PAGES).mkdir()
    (reports / R.PAGES / "old.md").write_text("# old\n")
    R.write_report(make_inputs(reports), providers(CONFIGURATIONS))
    assert not (reports / R.PAGES / "old.md").exists()
    assert (reports / R.PAGES / "fusion.md").is_file()


def test_renderer_robust_to_missing_files(tmp_path: Path) -> None:
    rep_dir = tmp_path / "reports"
    (rep_dir / "metrics").mkdir(parents=True)
    (rep_dir / "metrics" / "risk.json").write_text(
        json.dumps(
            {
                "main_variant": "v",
                "models": {"v": {"test/mse": 0.02}},
                "baselines": {"train_mean": {"test/mse": 0.03}},
            }
        )
    )
    inputs = M.ReportInputs(reports_dir=rep_dir, profile="default", seed=1, git_commit="c0ffee")
    rep = R.write_report(inputs, providers({}))
    check_report(rep_dir, {}, {})
    md = all_md(rep_dir)
    assert "`reports/metrics/fusion.json` is missing" in page_md(rep_dir, "fusion")
    assert "metrics/risk.json#models.v.at_1.5s.accuracy" in rep.missing  # named, shown as n/a
    assert (
        "| v | n/a | main | n/a | 0.02 | n/a | n/a | n/a |" in md
    )  # MSE, MAE, THW error, accuracy
    assert "| train_mean | n/a | baseline | n/a | 0.03 | n/a |" in md


def test_bad_metrics_file_named(tmp_path: Path) -> None:
    rep_dir = tmp_path / "reports"
    (rep_dir / "metrics").mkdir(parents=True)
    (rep_dir / "metrics" / "fusion.json").write_text("{not json")
    with pytest.raises(ValueError, match="fusion.json: not readable JSON"):
        R.write_report(
            M.ReportInputs(reports_dir=rep_dir, profile="ci", seed=1, git_commit="x"), providers({})
        )
    assert not (rep_dir / "README.md").exists()


def test_check_report_catches_a_wrong_number(reports: Path) -> None:
    """The verifier itself fails when a number in the HTML disagrees with its file."""
    inputs = make_inputs(reports)
    R.write_report(inputs, providers(CONFIGURATIONS))
    check_report(reports, dict(inputs.run_params), CONFIGURATIONS)
    for name, good, bad in (
        ("fusion", ">0.15<", ">0.16<"),
        ("risk", ">72.87 %<", ">72.88 %<"),
    ):  # a metrics value, a paper value, each on its page
        html = reports / R.PAGES / f"{name}.html"
        page = html.read_text()
        assert good in page
        html.write_text(page.replace(good, bad, 1))
        with pytest.raises(AssertionError):
            check_report(reports, dict(inputs.run_params), CONFIGURATIONS)
        html.write_text(page)


def test_paper_numbers_agree_with_risk_evaluation() -> None:
    """evaluate_risk keeps its own copy of the paper's figures (risk_metrics.PAPER): they must agree."""
    from traffictwin.risk.evaluation import PAPER

    assert PAPER["test/mse"] == P.RISK["test_mse"].value
    assert round(100 * PAPER["accuracy"], 2) == P.RISK["accuracy"].value
    assert round(100 * PAPER["wang_kato_accuracy"], 2) == P.RISK["wang_kato_accuracy"].value
    assert PAPER["threshold_s"] == P.RISK["thw_threshold_s"].value
    assert PAPER["confusion"] == {k: v.value for k, v in P.RISK_CONFUSION.items()}
    assert PAPER["n_frames"] == P.RISK["n_effective"].value


# --------------------------------------------------------------------------- the ci DAG's report
def _stage_inputs(
    repo: Path,
) -> tuple[dict[str, Any], dict[str, tuple[float, float]], dict[str, Any]]:
    """run_params, configurations and acceptance thresholds exactly as the report stage derives
    them from the repo's params.yaml."""
    from pipelines.report import profile_keys, run_params
    from traffictwin.acceptance import for_problem
    from traffictwin.config import load_params

    cfg = load_params(repo / "params.yaml")
    confs = {k: (float(v["r"]), float(v["alpha"])) for k, v in cfg["configurations"].items()}
    acceptance = {p: for_problem(cfg, p) for p in ("fusion", "risk", "stereo", "twin")}
    return run_params(cfg, profile_keys(repo / "conf" / "profile")), confs, acceptance


@pytest.mark.slow
@pytest.mark.xdist_group("ci_dag_dvc")  # DVC commands in the shared ci DAG: one at a time
def test_report_stage_on_ci_dag(ci_dag: Path, tmp_path: Path) -> None:
    from conftest import run

    reports = ci_dag / "reports"
    for name in ("README.md", "index.html", "results_table.md"):
        assert (reports / name).is_file(), name
    run_params, confs, acceptance = _stage_inputs(ci_dag)
    # every page, and every link resolves
    checked = check_report(reports, run_params, confs, acceptance)
    md = all_md(reports)  # the index and every page
    # both papers' headline tables, with numbers from the real metrics files
    for anchor_title in (
        "Fusion: KLD(b) mean",
        "Fusion: estimates with 95 % intervals",  # with its Dice columns
        "| Dice occ | 95 % CI | Dice free | 95 % CI |",
        "Every target of this run against its acceptance threshold",
        "Risk: test results",
        "Risk: confusion matrix",
        "Parameters of this run",
    ):
        assert anchor_title in md, anchor_title
    assert checked > 200
    # the report knows the real files' layout: nothing it looked for is missing
    assert "## Missing values" not in md
    # every stage that ran recorded its time in its run record (not in the report)
    records = [json.loads(p.read_text()) for p in (reports / "timings").glob("*.json")]
    assert all(r["seconds"] >= 0 for r in records if "stage" in r) and len(records) > 5
    assert "Stage wall times" not in md
    # the DVC metrics: the two summaries (each problem's headline test numbers and its training's
    # best-epoch validation numbers, what `dvc exp show` compares); every detailed metrics file
    # is an output shown in the report
    shown = json.loads(run(["dvc", "metrics", "show", "--json"], ci_dag).stdout)
    declared = {p for rev in shown.values() for p in rev.get("data", {})}
    assert declared == {
        "reports/metrics/summary_fusion.json",
        "reports/metrics/summary_risk.json",
    }, declared
    summary = json.loads((reports / "summary.json").read_text())
    assert set(summary) == {"run", "fusion", "risk", "twin"}  # run.note: the ci smoke banner
    assert summary["run"]["note"] == "ci profile: a smoke run; numbers are not results"
    assert set(summary["fusion"]) == set(confs)
    table = run(["dvc", "metrics", "show"], ci_dag).stdout
    assert len(table.splitlines()) <= 40, table
    rep = rebuilt_report(reports, run_params, confs, acceptance)
    sources = [c.src or "" for s in rep.sections for t in s.tables for r in t.rows for c in r]
    for f in (p.name for p in (reports / "metrics").glob("*.json")):
        assert any(x.startswith(f"metrics/{f}#") for x in sources), f
    # every figure (plot_data draws them all) is in the report
    for p in (reports / "figures").glob("*.png"):
        assert f"figures/{p.name}" in md, p.name
    # dvc plots: every declared plot renders (tests/test_plots.py checks their fields)
    plots = json.loads(
        run(["dvc", "plots", "show", "--json", "-o", str(tmp_path / "plots")], ci_dag).stdout
    )["data"]
    for pid in (
        "fusion_kld_box",
        "reports/charts/fusion_scores.csv",
        "reports/charts/fusion_learning_curves.csv",
        "reports/charts/registration_learning_curves.csv",
        "reports/charts/risk_learning_curves.csv",
        "reports/charts/risk_roc.csv",
        "reports/charts/risk_pr.csv",
        "reports/plots/risk_confusion.csv",
        "reports/plots/twin_timeline.csv",
    ):
        assert pid in plots, pid
        assert all(not r.get("errors") and r.get("content") for r in plots[pid]), (pid, plots[pid])


def test_stage_helpers(tmp_path: Path) -> None:
    """pipelines.report: dirty check ignores pipeline-written files; profile keys."""
    import subprocess

    from omegaconf import OmegaConf

    from pipelines.report import git_dirty, profile_keys, run_params

    git = ["git", "-c", "user.email=t@t", "-c", "user.name=t", "-c", "commit.gpgsign=false"]
    (tmp_path / "src").mkdir()
    (tmp_path / "src" / "a.py").write_text("x = 1\n")
    (tmp_path / "dvc.lock").write_text("a\n")
    subprocess.run([*git, "init", "-q"], cwd=tmp_path, check=True)
    subprocess.run([*git, "add", "-A"], cwd=tmp_path, check=True)
    subprocess.run([*git, "commit", "-q", "-m", "c"], cwd=tmp_path, check=True)
    assert not git_dirty(tmp_path)
    (tmp_path / "dvc.lock").write_text("b\n")
    assert not git_dirty(tmp_path)  # the pipeline rewrites dvc.lock itself
    (tmp_path / "src" / "a.py").write_text("x = 2\n")
    assert git_dirty(tmp_path)

    cfg = OmegaConf.create(
        {
            "m": {"vs": ["x", "y"]},
            "seed": 3,
            "sizes": {"n": 5, "k": 2},
            "data": {"seed": 9, "other": 1},
        }
    )
    prof = tmp_path / "profile"
    prof.mkdir()
    (prof / "ci.yaml").write_text(
        "# @package _global_\ndefaults:\n  - override /trainer: gpu\nprofile: {name: ci}\nsizes: {n: 1}\n"
    )
    assert profile_keys(prof) == {"profile.name", "sizes.n"}
    assert run_params(cfg, profile_keys(prof)) == {"seed": 3, "sizes.n": 5, "data.seed": 9}


def test_report_bytes_do_not_follow_the_commit(reports: Path) -> None:
    """The commit (like the experiment's name and the pipeline run id, which the report's inputs
    do not even hold) goes to the report stage's run record; the report is the same bytes for any
    commit, so ``dvc repro -f`` leaves ``dvc.lock`` unchanged."""
    from dataclasses import replace

    inputs = make_inputs(reports)
    R.write_report(inputs, providers(CONFIGURATIONS))
    files = [*page_files(reports), *page_files(reports, html=True)]
    first = {p.relative_to(reports).as_posix(): p.read_bytes() for p in files}
    assert len(first) > 2
    other = replace(inputs, git_commit="fedcba987654")
    R.write_report(other, providers(CONFIGURATIONS))
    for name, data in first.items():
        assert (reports / name).read_bytes() == data, name
    md = first["README.md"].decode()
    assert "abc123" not in md and "fedcba98" not in md
    assert "reports/timings/report.json" in md


def test_smoke_profile_banner_on_report_summary_and_plot_titles(reports: Path) -> None:
    repo = Path(__file__).resolve().parents[1]
    """On the ci profile the report, summary.json (the DVC metrics file) and every plot
    title say it is a smoke run; on the default profile nothing does."""
    from dataclasses import replace

    import yaml

    ci = yaml.safe_load((repo / "conf" / "profile" / "ci.yaml").read_text())["profile"]["banner"]
    assert "smoke run" in ci and "not results" in ci
    for prof in ("default", "paper"):
        conf = yaml.safe_load((repo / "conf" / "profile" / f"{prof}.yaml").read_text())
        assert conf["profile"]["banner"] == ""
    R.write_report(replace(make_inputs(reports), banner=ci), providers(CONFIGURATIONS))
    md = (reports / "README.md").read_text()  # the index: the banner on the first screen
    first = md.split("\n\n")[1]  # the paragraph after the title
    assert first == "**ci profile: a smoke run; numbers are not results.**", first
    assert "smoke run" in (reports / "index.html").read_text()
    summary = json.loads((reports / "summary.json").read_text())
    assert summary["run"] == {"note": "ci profile: a smoke run; numbers are not results"}
    R.write_report(make_inputs(reports), providers(CONFIGURATIONS))
    assert "smoke run" not in (reports / "README.md").read_text()
    assert "run" not in json.loads((reports / "summary.json").read_text())
    dvc = yaml.safe_load((repo / "dvc.yaml").read_text())
    titles = [p[k]["title"] for p in dvc["plots"] for k in p if "title" in (p[k] or {})]
    for st in dvc["stages"].values():
        body = st.get("do", st)
        for p in body.get("plots", []):
            for props in p.values() if isinstance(p, dict) else ():
                if isinstance(props, dict) and "title" in props:
                    titles.append(props["title"])
    assert len(titles) >= 10
    assert all(t.endswith("${profile.banner}") for t in titles), titles


def test_html_cells_align_numbers_right_and_text_left(reports: Path) -> None:
    """Text columns read left-aligned; numbers, intervals and percentages right-aligned (class
    ``num``), n/a greyed: the class a cell gets decides it, the style sheet says so."""
    for text in ("reproduced", "Sec. V-A, Fig. 5", "hybrid_s2", "A 0.001 vs B 0.002"):
        assert R.cell_class(text) is None, text
    for text in ("0.940", "[0.910, 0.965]", "99.73 %", "-0.131", "+0.0010", "1,234", "12.3 ms"):
        assert R.cell_class(text) == "num", text
    assert R.cell_class(M.NA) == "na"
    R.write_report(make_inputs(reports), providers(CONFIGURATIONS))
    html = page_html(reports, "risk")  # the HTML's cells carry the class of their text
    assert '<td class="num">72.87 %</td>' in html and "<td>paper (Feth et al.)</td>" in html
    css = (reports / R.STYLE).read_text()
    assert "text-align:left" in css.split("td.num")[0] and "td.num{text-align:right" in css
