"""Copy the committed results into README.md and docs/ between markers (``make readme``).

What goes where, each block from files that ``make run`` / ``make bench`` write:

- README.md, *Headline results*: three small tables (fusion, risk, twin) with their 95 % intervals,
  from ``reports/metrics/{fusion,risk,twin}.json`` and the configurations of ``params.yaml``;
- README.md, *How long it takes*: the default run's wall time and stage time, from the run records
  ``reports/timings/*.json``;
- docs/results.md: the report's headline tables (``reports/results_table.md``) and the timing table
  per part of the pipeline (the run records);
- docs/benchmarks.md: the figures of ``reports/benchmarks.json``.

``tests/test_readme.py`` fails when a page shows other numbers than the committed files, so they
cannot drift apart silently. ``make docs`` also runs :mod:`pipelines.docs_reference` (CLI reference,
test counts).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from datetime import datetime
from pathlib import Path
from typing import Any

from traffictwin.io.atomic import write_text_atomic
from traffictwin.report.model import fmt_value
from traffictwin.report.render import RESULTS_TABLE

from ._paths import REPORTS, ROOT

README = "README.md"
RESULTS_PAGE = "docs/results.md"
BENCH_PAGE = "docs/benchmarks.md"

BEGIN = "<!-- results:begin (generated from reports/results_table.md by `make readme`) -->"
END = "<!-- results:end -->"
T_BEGIN = "<!-- timings:begin (generated from reports/timings/*.json by `make readme`) -->"
T_END = "<!-- timings:end -->"
H_BEGIN = (
    "<!-- headline:begin (generated from reports/metrics/{fusion,risk,twin}.json "
    "by `make readme`) -->"
)
H_END = "<!-- headline:end -->"
TS_BEGIN = "<!-- run-time:begin (generated from reports/timings/*.json by `make readme`) -->"
TS_END = "<!-- run-time:end -->"
B_BEGIN = "<!-- benchmarks:begin (generated from reports/benchmarks.json by `make readme`) -->"
B_END = "<!-- benchmarks:end -->"

#: the wall time (min) `make run` (the default DAG) should take on a 2-core machine
RUN_BUDGET_MIN = 25.0
#: how many of the longest stages the README's run-time table names
LONGEST_SHOWN = 3

#: a pause longer than this between one stage's end and the next one's start is not part of the run
#: (a stage re-run on its own later, e.g. `dvc repro report` after a fix)
GAP_S = 300.0

# timing rows: (what, stage names or prefixes before "@")
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

# README headline tables: (key in fusion.json's test.<cfg>, column title)
FUSION_METHODS = (
    ("naive", "naive: noisy pose + Dempster"),
    ("registered", "registered (FM + ECC) + Dempster"),
    ("dnn", "network"),
    ("learned+network", "learned registration + network"),
)
# (key in twin.json's targets, quantity, number format of value and interval)
TWIN_TARGETS = (
    ("occluded_recall_ge_0.9", "occluded: critical frames the twin flags (target ≥ 90 %)", "pct"),
    (
        "occluded_recall_above_ego",
        "occluded: critical frames flagged, twin minus the ego's own map (target: CI > 0)",
        "pct",
    ),
    (
        "occluded_median_lead_vs_ego_ge_0.8s",
        "occluded: median warning lead over the ego's own map, s (target ≥ 0.8 s)",
        "f2",
    ),
    (
        "occluded_warned_before_onset_ge_0.95",
        "occluded: episodes warned before their onset (target ≥ 95 %)",
        "pct",
    ),
    (
        "open_false_alarms_le_0.05_frame_noise",
        "open: false-alarm frames, per-frame pose noise (target ≤ 5 %)",
        "pct",
    ),
    (
        "open_false_alarms_le_0.05_pose_bias",
        "open: false-alarm frames, persistent pose bias (target ≤ 5 %)",
        "pct",
    ),
)


# ------------------------------------------------------------------ blocks
def results_block(table_md: str, reports_link: str = "../reports/README.md") -> str:
    """The results page's block for ``table_md``: the table without its generated-file comment or
    link line; links to the report point at ``reports_link`` (relative to docs/), links to its
    pages (``pages/<name>.md``) at the same pages beside it."""
    lines = [
        ln
        for ln in table_md.splitlines()
        if not ln.startswith("<!--") and not ln.startswith("Full report:")
    ]
    reports = reports_link.rsplit("/", 1)[0]
    body = (
        "\n".join(lines)
        .strip()
        .replace("](README.md)", f"]({reports_link})")
        .replace("](pages/", f"]({reports}/pages/")
    )
    return f"{BEGIN}\n{body}\n{END}"


def _minutes(seconds: float) -> str:
    return f"{seconds / 60:.1f} min"


def _t(s: str) -> datetime:
    return datetime.strptime(s, "%Y-%m-%dT%H:%M:%SZ")


def sessions(records: list[dict]) -> list[list[dict]]:
    """The timed records (``started`` / ``finished``) in start order, split where a stage started
    more than :data:`GAP_S` after every earlier one had finished."""
    timed = sorted(
        (r for r in records if "started" in r and "finished" in r), key=lambda r: _t(r["started"])
    )
    out: list[list[dict]] = []
    end = None
    for r in timed:
        if end is None or (_t(r["started"]) - end).total_seconds() > GAP_S:
            out.append([])
            end = _t(r["finished"])
        out[-1].append(r)
        end = max(end, _t(r["finished"]))
    return out


def wall_seconds(records: list[dict]) -> float | None:
    """The run's wall time (s): the sum of the sessions' spans (first stage start to last stage
    end of each, :func:`sessions`); None without timed records."""
    parts = sessions(records)
    if not parts:
        return None
    return sum(
        (max(_t(r["finished"]) for r in s) - min(_t(r["started"]) for r in s)).total_seconds()
        for s in parts
    )


def _wall_row(records: list[dict]) -> str | None:
    """The table row of the run's wall time (:func:`wall_seconds`), the machine and its load;
    None without timed records."""
    parts = sessions(records)
    span = wall_seconds(records)
    if span is None:
        return None
    timed = [r for s in parts for r in s]
    machines = {(r["machine"]["cpu"], r["machine"]["cpu_count"]) for r in timed if "machine" in r}
    loads = [r["machine"]["load_start"][0] for r in timed if r.get("machine", {}).get("load_start")]
    where = "; ".join(f"{cpu}, {n} cores" for cpu, n in sorted(machines))
    load = (
        f", 1-min load average at the stages' starts {min(loads):.1f}–{max(loads):.1f}"
        if loads
        else ""
    )
    later = ""
    if len(parts) > 1:  # the run is the session with the most stages; the others ran apart
        main = max(range(len(parts)), key=lambda i: len(parts[i]))
        names = ", ".join(f"`{r['stage']}`" for i, s in enumerate(parts) if i != main for r in s)
        later = f", without the pauses around {names}, run on its own at another time"
    return (
        f"| `make run`: the whole default DAG, wall (first stage start to last stage end{later}; "
        f"{where}{load}) | **{_minutes(span)}** |"
    )


def _sum_row(records: list[dict]) -> str:
    total = sum(float(r.get("seconds", 0.0)) for r in records)
    return (
        f"| — the stages' own time (sum of the run records, {len(records)} stages) "
        f"| {_minutes(total)} |"
    )


def timings_block(records: list[dict]) -> str:
    """The results page's timing table from the run records of one ``dvc repro``: the wall time,
    the sum of the stages' times, the machine and its load, and the stage time per part of the
    pipeline."""
    lines = [T_BEGIN, "| what | time |", "| --- | --- |"]
    wall = _wall_row(records)
    lines += [wall] if wall else []
    lines.append(_sum_row(records))
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


def run_time_block(records: list[dict]) -> str:
    """The README's timing table: the default run's wall time, the stages' own time, the
    :data:`LONGEST_SHOWN` longest stages, and the run against :data:`RUN_BUDGET_MIN`."""
    wall = _wall_row(records)
    rows = ([wall] if wall else []) + [_sum_row(records)]
    timed = sorted(
        (r for r in records if float(r.get("seconds", 0.0)) > 0),
        key=lambda r: -float(r["seconds"]),
    )[:LONGEST_SHOWN]
    if timed:
        names = ", ".join(f"`{r['stage']}` {float(r['seconds']) / 60:.1f}" for r in timed)
        total = sum(float(r["seconds"]) for r in timed)
        rows.append(f"| — the {len(timed)} longest stages: {names} min | {_minutes(total)} |")
    span = wall_seconds(records)
    if span is not None:
        over = span / 60 - RUN_BUDGET_MIN
        verdict = f"{over:.1f} min over it" if over > 0 else "within it"
        rows.append(
            f"| the budget of `make run` on a 2-core machine | {RUN_BUDGET_MIN:g} min "
            f"(the run above: {verdict}) |"
        )
    return "\n".join([TS_BEGIN, "| what | time |", "| --- | --- |", *rows, TS_END])


def _get(d: Any, dotted: str) -> Any:
    for k in dotted.split("."):
        if not isinstance(d, Mapping) or k not in d:
            return None
        d = d[k]
    return d


def _ci_cell(value: Any, ci: Any, fmt: str) -> str:
    """``value [lo, hi]`` (``ci`` as ``{"lo", "hi"}`` or ``[lo, hi]``); ``n/a`` without a value."""
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        return "n/a"
    if isinstance(ci, Mapping):
        lo, hi = ci.get("lo"), ci.get("hi")
    elif isinstance(ci, (list, tuple)) and len(ci) == 2:
        lo, hi = ci
    else:
        return fmt_value(value, fmt)
    return f"{fmt_value(value, fmt)} [{fmt_value(lo, fmt)}, {fmt_value(hi, fmt)}]"


def _g(v: Any) -> str:
    return f"{float(v):g}"


def fusion_table(fusion: Mapping, configurations: Mapping) -> list[str]:
    """KLD(b) per configuration for the baseline, classical registration, the network and the best
    learned combination (``fusion.json``: ``test.<cfg>.<method>.kld_fou_mean`` and its CI)."""
    test = fusion.get("test") if isinstance(fusion, Mapping) else None
    if not isinstance(test, Mapping) or not test:
        return []
    n = _get(fusion, "n_pairs.per_config")
    pairs = f"{n} test pairs per configuration" if n else "test pairs"
    lines = [
        f"**Fusion: KLD(b) per pose-noise configuration ({pairs}; lower is better)**",
        "",
        "| config (r, α) | " + " | ".join(title for _, title in FUSION_METHODS) + " |",
        "| --- |" + " --- |" * len(FUSION_METHODS),
    ]
    for cfg in sorted(test):
        c = configurations.get(cfg, {}) if isinstance(configurations, Mapping) else {}
        label = f"{cfg} ({_g(c['r'])} m, {_g(c['alpha'])}°)" if "r" in c and "alpha" in c else cfg
        cells = [
            _ci_cell(
                _get(test, f"{cfg}.{m}.kld_fou_mean"),
                _get(test, f"{cfg}.{m}.kld_fou_mean_ci"),
                "g4",
            )
            for m, _ in FUSION_METHODS
        ]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines


def risk_table(risk: Mapping) -> list[str]:
    """ROC-AUC and balanced accuracy at the first THW threshold for the shipped predictor, the SGM
    corridor rule, the DAVE-2 headline network (seed mean) and the speed-only baseline."""
    ts = _get(risk, "thresholds_s")
    if not isinstance(ts, list) or not ts:
        return []
    at = f"at_{float(ts[0]):g}s"
    shipped_from = _get(risk, "selection.shipped_from")
    main = _get(risk, "main_variant") or "headline"
    n_seeds = _get(risk, f"groups.{main}.n_seeds")
    rows = (
        (
            f"shipped predictor (`{shipped_from}`, chosen on validation)"
            if shipped_from
            else "shipped predictor",
            "models.shipped",
        ),
        ("baseline: corridor rule on SGM disparity", "baselines.geometric_sgm"),
        (
            f"DAVE-2 network `{main}` (mean of {n_seeds} seeds)"
            if n_seeds
            else f"DAVE-2 network `{main}`",
            f"groups.{main}" if n_seeds else f"models.{main}",
        ),
        ("baseline: speed only", "baselines.speed_only"),
    )
    n_frames, n_seq = _get(risk, "n_frames.test"), _get(risk, "n_sequences.test")
    where = f"{n_frames} test frames of {n_seq} sequences" if n_frames and n_seq else "test frames"
    lines = [
        f"**Risk: critical frames (THW < {float(ts[0]):g} s), {where}; higher is better**",
        "",
        "| predictor | ROC-AUC | balanced accuracy |",
        "| --- | --- | --- |",
    ]
    for label, key in rows:
        row = _get(risk, key)
        row = row.get(at) if isinstance(row, Mapping) else None
        if not isinstance(row, Mapping):
            continue
        auc = _ci_cell(row.get("roc_auc"), row.get("roc_auc_ci"), "f3")
        bacc = _ci_cell(row.get("balanced_accuracy"), row.get("balanced_accuracy_ci"), "f3")
        lines.append(f"| {label} | {auc} | {bacc} |")
    return lines


def twin_table(twin: Mapping) -> list[str]:
    """A few of the twin's targets (``twin.json``: ``targets``): value, interval, met."""
    targets = _get(twin, "targets")
    if not isinstance(targets, Mapping):
        return []
    rows = []
    for key, quantity, fmt in TWIN_TARGETS:
        t = targets.get(key)
        if not isinstance(t, Mapping) or "value" not in t:
            continue
        met = "yes" if t.get("met") is True else "no" if t.get("met") is False else "n/a"
        rows.append(f"| {quantity} | {_ci_cell(t['value'], t.get('ci'), fmt)} | {met} |")
    if not rows:
        return []
    who = f"twin `{targets.get('method')}`" if targets.get("method") else "the twin"
    cfg = f" at configuration {targets['configuration']}" if targets.get("configuration") else ""
    return [
        f"**Cooperative twin: {who}{cfg}, occluded and open sequences**",
        "",
        "| quantity | value [95 % CI] | met |",
        "| --- | --- | --- |",
        *rows,
    ]


def headline_block(
    fusion: Mapping, risk: Mapping, twin: Mapping, configurations: Mapping | None = None
) -> str:
    """The README's three small headline tables between :data:`H_BEGIN` / :data:`H_END`."""
    parts = [
        t
        for t in (
            fusion_table(fusion, configurations or {}),
            risk_table(risk),
            twin_table(twin),
        )
        if t
    ]
    body = "\n\n".join("\n".join(t) for t in parts) or "No results yet (run `make run`)."
    note = (
        "<sub>Brackets: 95 % bootstrap intervals (fusion: scenarios resampled; risk: driving "
        "sequences, and seeds for a seed group; twin: sequences).</sub>"
    )
    return f"{H_BEGIN}\n{body}\n\n{note}\n{H_END}"


def _ms(v: Any) -> str:
    return f"{float(v):.3g}"


def _machine(b: Mapping) -> str:
    """Where a benchmark ran, from the different ways the benchmarks record it."""
    m = b.get("machine")
    if isinstance(m, str):
        return m
    m = m if isinstance(m, Mapping) else {}
    cpu = m.get("cpu") or b.get("cpu")
    cores = m.get("cores", m.get("cpus"))
    load = m.get("load_avg_1min", m.get("loadavg_1min", m.get("load_avg_1m")))
    if load is None and isinstance(b.get("load_average"), list) and b["load_average"]:
        load = b["load_average"][0]
    threads = m.get("torch_threads", b.get("torch_threads"))
    parts = [str(cpu)] if cpu else []
    parts += [f"{cores} cores"] if cores else []
    parts += [f"{threads} torch threads"] if threads else []
    parts += [f"load {float(load):.1f}"] if load is not None else []
    return ", ".join(parts)


def _bench_fusion_data(b: Mapping) -> tuple[str, str]:
    return (
        "fusion data generation (1 core; world, traffic, 2 lidar scans + 2 ISMs per "
        "encounter, warps, Dempster)",
        f"{b['generation_pairs_per_s_1core']:.1f} pairs/s",
    )


def _bench_fusion_steps(b: Mapping) -> tuple[str, str]:
    g = b["grid"]
    return (
        f"lidar scan ({b['lidar_rays']} rays) / ISM / Dempster / SE(2) warp of a "
        f"{g[0]}×{g[1]} grid",
        f"{_ms(b['lidar_scan_ms'])} / {_ms(b['ism_ms'])} / {_ms(b['dempster_ms'])} / "
        f"{_ms(b['warp_ms'])} ms",
    )


def _bench_risk_data(b: Mapping) -> tuple[str, str]:
    return (
        f"stereo rendering {b['resolution']} / SGM / ORB check / risk metric",
        f"{b['render_pairs_per_s']:.1f} pairs/s / {b['sgm_frames_per_s']:.0f} / "
        f"{b['orb_frames_per_s']:.0f} / {b['risk_metric_frames_per_s']:.0f} frames/s",
    )


def _bench_net(key: str, title: str) -> Callable[[Mapping], tuple[str, str]]:
    """The row maker of the fusion network ``key`` of the ``fusion_model`` benchmark."""

    def make(b: Mapping) -> tuple[str, str]:
        n = b[key]
        return (
            f"{title}, {n['param_count']:,} params: training at batch {n['train_batch']} / "
            "inference at batch 1 / at batch 8",
            f"{n['train_samples_per_s']:.3g} samples/s / {_ms(n['infer_ms_per_pair_batch1'])} / "
            f"{_ms(n['infer_ms_per_pair_batch8'])} ms per pair",
        )

    return make


def _bench_paper_estimate(b: Mapping) -> tuple[str, str]:
    n = b["paper_resnet50"]
    return (
        "paper profile fusion training (10,000 pairs, 200 epochs), estimated from the "
        "measured step time and from FLOPs",
        f"~{n['paper_profile_estimate_h_on_this_cpu']:.0f} h on this CPU; "
        f"~{n['paper_profile_estimate_h_gpu_at_100_tflops']:.1f} h at 100 TFLOP/s "
        "(not measured: no GPU)",
    )


def _bench_registration(b: Mapping) -> tuple[str, str]:
    ms = b["learned_ms_per_pair"]
    return (
        f"registration per pair at configuration {b['cfg']} ({b['pairs']} test pairs): learned "
        "(estimate + fallback check + warp + Dempster) at batch 1 / batch 8 / the estimate "
        "alone; classical FM + ECC + warp + Dempster",
        f"{_ms(ms['batch_1'])} / {_ms(ms['batch_8'])} / {_ms(b['learned_estimate_ms_per_pair'])} "
        f"ms; {_ms(b['registered_ms_per_pair'])} ms",
    )


def _bench_twin(b: Mapping) -> tuple[str, str]:
    per = b["ms_per_step"]
    ns = sorted({int(n) for m in per.values() for n in m})
    methods = [m for m in ("naive", "learned", "learned+network", "registered") if m in per]
    figs = "; ".join(
        f"{m}: " + " / ".join(_ms(per[m][str(n)]) if str(n) in per[m] else "n/a" for n in ns)
        for m in methods
    )
    return (
        f"twin update per step at configuration {b['cfg']} ({b['strategy']} strategy) for "
        f"N = {' / '.join(str(n) for n in ns)} vehicles",
        f"{figs} ms",
    )


def _bench_cli(b: Mapping) -> tuple[str, str]:
    f, r = b["fuse"], b["risk"]
    what = (
        f"`traffictwin fuse` per pair ({f['grid'][0]}×{f['grid'][1]}, {f['model']}): prealign + "
        f"model; `traffictwin risk` per frame ({r['image'][0]}×{r['image'][1]}, "
        f"`{r['model']}`): ORB + SGM + model"
    )
    figs = (
        f"{_ms(f['prealign_ms'])} + {_ms(f['model_ms_per_pair'])} = "
        f"{_ms(f['total_ms_per_pair'])} ms; {_ms(r['orb_ms'])} + {_ms(r['sgm_ms'])} + "
        f"{_ms(r['model_ms_per_frame'])} = {_ms(r['total_ms_per_frame'])} ms"
    )
    ls = r.get("learned_stereo")
    if ls:
        what += f"; with the learned stereo network (`{ls['model']}`): ORB + SGM + network + model"
        figs += (
            f"; {_ms(r['orb_ms'])} + {_ms(r['sgm_ms'])} + {_ms(ls['stereo_ms_per_frame'])} + "
            f"{_ms(r['model_ms_per_frame'])} = {_ms(ls['total_ms_per_frame'])} ms"
        )
    return what, figs


def _bench_ci_dag(b: Mapping) -> tuple[str, str]:
    return (
        f"`ci` profile, whole DAG (`dvc repro` after `-S profile=ci`, in a clone of commit "
        f"{b.get('commit', '?')}; the Quick start)",
        f"{b['wall_s']:.0f} s wall: {b['stages']} stage processes, {b['in_stage_s']:.0f} s "
        f"inside the stages, {b['outside_stage_s']:.0f} s process start, imports and DVC; "
        f"nothing to do: {b['noop_s']:.0f} s",
    )


#: (benchmark in reports/benchmarks.json, its row's maker: b -> (what, figure)), in table order
BENCH_ROWS: tuple[tuple[str, Callable[[Mapping], tuple[str, str]]], ...] = (
    ("fusion_data", _bench_fusion_data),
    ("fusion_data", _bench_fusion_steps),
    ("risk_data", _bench_risk_data),
    (
        "fusion_model",
        _bench_net("default_resnet18-w16", "default fusion net (narrow ResNet-18 DeepLabV3+)"),
    ),
    ("fusion_model", _bench_net("paper_resnet50", "paper fusion net (ResNet-50 DeepLabV3+)")),
    ("fusion_model", _bench_paper_estimate),
    ("registration", _bench_registration),
    ("twin", _bench_twin),
    ("cli_latency", _bench_cli),
    ("ci_dag", _bench_ci_dag),
)


def _bench_rows(bench: Mapping) -> list[tuple[str, str, str]]:
    """``(what, figure, machine)`` per benchmark figure in ``bench`` (``benchmarks`` of
    reports/benchmarks.json); a benchmark that did not run, or lacks a key, gives no row."""
    rows: list[tuple[str, str, str]] = []
    for name, make in BENCH_ROWS:
        b = bench.get(name)
        if not isinstance(b, Mapping):
            continue
        try:
            what, fig = make(b)
        except (KeyError, TypeError, ValueError):
            continue
        rows.append((f"{what} (`{name}`)", fig, _machine(b)))
    return rows


def benchmarks_block(results: Mapping) -> str:
    """docs/benchmarks.md's table of ``reports/benchmarks.json`` (``make bench``)."""
    env = results.get("environment") if isinstance(results, Mapping) else None
    env = env if isinstance(env, Mapping) else {}
    bench = results.get("benchmarks") if isinstance(results, Mapping) else None
    rows = _bench_rows(bench if isinstance(bench, Mapping) else {})
    lines = [B_BEGIN]
    if env:
        torch = _get(env, "packages.torch")
        gpu = env.get("gpu") or "no GPU"
        lines += [
            f"Last `make bench`: {env.get('cpu')}, {env.get('cpu_count')} cores, "
            f"{env.get('memory_gb')} GB, {gpu}; Python {env.get('python')}"
            + (f", torch {torch}" if torch else "")
            + ".",
            "",
        ]
    lines += ["| what | figure | machine |", "| --- | --- | --- |"]
    lines += [f"| {w} | {f} | {m} |" for w, f, m in rows]
    lines.append(B_END)
    return "\n".join(lines)


# ------------------------------------------------------------------ pages
def replace_block(text: str, begin: str, end: str, block: str, name: str = "README.md") -> str:
    """``text`` with everything from ``begin`` to ``end`` (the markers included) replaced by
    ``block`` (which starts with ``begin`` and ends with ``end``)."""
    if begin not in text or end not in text:
        raise ValueError(f"{name}: markers missing ({begin!r} … {end!r})")
    head, rest = text.split(begin, 1)
    _, tail = rest.split(end, 1)
    return head + block + tail


def read_records(folder) -> list[dict]:
    """Every run record ``<folder>/*.json``, in name order."""
    return [json.loads(p.read_text()) for p in sorted(Path(folder).glob("*.json"))]


def page_blocks(read: Callable[[str], str], records: list[dict]) -> dict[str, list[str]]:
    """``{page: [block, ...]}``: every generated block of every page, from the files ``read``
    returns (paths relative to the repository root) and the run records ``records``."""
    import yaml

    def js(rel: str) -> Any:
        try:
            return json.loads(read(rel))
        except (OSError, ValueError):
            return {}

    try:
        configurations = (yaml.safe_load(read("params.yaml")) or {}).get("configurations", {})
    except (OSError, ValueError):
        configurations = {}
    metrics = "reports/metrics/"
    return {
        README: [
            headline_block(
                js(metrics + "fusion.json"),
                js(metrics + "risk.json"),
                js(metrics + "twin.json"),
                configurations,
            ),
            run_time_block(records),
        ],
        RESULTS_PAGE: [results_block(read(f"reports/{RESULTS_TABLE}")), timings_block(records)],
        BENCH_PAGE: [benchmarks_block(js("reports/benchmarks.json"))],
    }


def render(page: str, text: str, blocks: list[str]) -> str:
    """``text`` of ``page`` with each of ``blocks`` put between its markers (each block's first and
    last line)."""
    for block in blocks:
        lines = block.splitlines()
        text = replace_block(text, lines[0], lines[-1], block, page)
    return text


def main() -> None:
    records = read_records(REPORTS / "timings")
    blocks = page_blocks(lambda rel: (ROOT / rel).read_text(encoding="utf-8"), records)
    for page, items in blocks.items():
        path = ROOT / page
        write_text_atomic(path, render(page, path.read_text(encoding="utf-8"), items))
    print(f"{', '.join(blocks)}: generated blocks updated from reports/ and params.yaml")


if __name__ == "__main__":
    main()
