"""Copy the generated results table (reports/results_table.md) and the run's timings (the run
records reports/timings/*.json) into README.md between markers.

``make readme`` runs it after ``make run``; ``tests/test_readme.py`` fails when README.md shows
other numbers than the committed report and run records, so they cannot drift apart silently.
"""

from __future__ import annotations

from traffictwin.io.atomic import write_text_atomic
from traffictwin.report.render import RESULTS_TABLE

from ._paths import REPORTS, ROOT

BEGIN = "<!-- results:begin (generated from reports/results_table.md by `make readme`) -->"
END = "<!-- results:end -->"
T_BEGIN = "<!-- timings:begin (generated from reports/timings/*.json by `make readme`) -->"
T_END = "<!-- timings:end -->"
# README rows: (what, stage names or prefixes before "@")
TIMING_GROUPS = (
    (
        "fusion data: `generate_fusion`, `prealign@*`, `prealign_mixed`, `register@*`",
        ("generate_fusion", "prealign", "prealign_mixed", "register"),
    ),
    (
        "fusion and registration training: `train_fusion`, `train_fusion_variant@*`, `train_registration`",
        ("train_fusion", "train_fusion_variant", "train_registration"),
    ),
    ("fusion evaluation: `evaluate_fusion`", ("evaluate_fusion",)),
    ("cooperative twin: `generate_twin`, `evaluate_twin`", ("generate_twin", "evaluate_twin")),
    (
        "risk data: `generate_risk`, `disparity`, `orb_filter`",
        ("generate_risk", "disparity", "orb_filter"),
    ),
    (
        "risk training, selection and evaluation: `train_risk@*`, `train_risk_hybrid`, "
        "`select_risk`, `evaluate_risk`",
        ("train_risk", "train_risk_hybrid", "select_risk", "evaluate_risk"),
    ),
    ("report: `environment`, `plot_data`, `report`", ("environment", "plot_data", "report")),
)


def results_block(table_md: str) -> str:
    """The README block for ``table_md``: the table without its generated-file comment or link line."""
    lines = [
        ln
        for ln in table_md.splitlines()
        if not ln.startswith("<!--") and not ln.startswith("Full report:")
    ]
    body = "\n".join(lines).strip().replace("](README.md)", "](reports/README.md)")
    return f"{BEGIN}\n{body}\n{END}"


def _minutes(seconds: float) -> str:
    return f"{seconds / 60:.1f} min"


def timings_block(records: list[dict]) -> str:
    """The README's timing table from the run records of one ``dvc repro``: the wall time (first
    stage start to last stage end), the sum of the stages' times, the machine and its load, and
    the stage time per part of the pipeline."""
    from datetime import datetime

    def t(s: str) -> datetime:
        return datetime.strptime(s, "%Y-%m-%dT%H:%M:%SZ")

    timed = [r for r in records if "started" in r and "finished" in r]
    total = sum(float(r.get("seconds", 0.0)) for r in records)
    lines = [T_BEGIN, "| what | time |", "| --- | --- |"]
    if timed:
        span = (
            max(t(r["finished"]) for r in timed) - min(t(r["started"]) for r in timed)
        ).total_seconds()
        machines = {
            (r["machine"]["cpu"], r["machine"]["cpu_count"]) for r in timed if "machine" in r
        }
        loads = [
            r["machine"]["load_start"][0] for r in timed if r.get("machine", {}).get("load_start")
        ]
        where = "; ".join(f"{cpu}, {n} cores" for cpu, n in sorted(machines))
        load = (
            f", 1-min load average at the stages' starts {min(loads):.1f}–{max(loads):.1f}"
            if loads
            else ""
        )
        lines.append(
            f"| `make run`: the whole default DAG, wall (first stage start to last stage end; {where}{load}) "
            f"| **{_minutes(span)}** |"
        )
    lines.append(
        f"| — the stages' own time (sum of the run records, {len(records)} stages) | {_minutes(total)} |"
    )
    for what, names in TIMING_GROUPS:
        secs = [
            float(r.get("seconds", 0.0))
            for r in records
            if str(r.get("stage", "")).split("@")[0] in names
        ]
        if secs:
            lines.append(f"| — {what} | {_minutes(sum(secs))} |")
    lines.append(T_END)
    return "\n".join(lines)


def read_records(folder) -> list[dict]:
    """Every run record ``<folder>/*.json``, in name order."""
    import json
    from pathlib import Path

    return [json.loads(p.read_text()) for p in sorted(Path(folder).glob("*.json"))]


def _replace(readme: str, begin: str, end: str, block: str) -> str:
    if begin not in readme or end not in readme:
        raise ValueError(f"README.md: markers missing ({begin!r} … {end!r})")
    head, rest = readme.split(begin, 1)
    _, tail = rest.split(end, 1)
    return head + block + tail


def render(readme: str, table_md: str, records: list[dict] | None = None) -> str:
    """``readme`` with the text between the markers replaced by :func:`results_block` (and, given
    ``records``, by :func:`timings_block`)."""
    out = _replace(readme, BEGIN, END, results_block(table_md))
    if records is not None:
        out = _replace(out, T_BEGIN, T_END, timings_block(records))
    return out


def main() -> None:
    readme = ROOT / "README.md"
    records = read_records(REPORTS / "timings")
    new = render(readme.read_text(), (REPORTS / RESULTS_TABLE).read_text(), records)
    write_text_atomic(readme, new)
    print("README.md: results and timings blocks updated from reports/")


if __name__ == "__main__":
    main()
