"""Stage evaluate_twin: the twin of every configuration and method, and the ego's risk from it.

Reads ``data/twin`` (generate_twin), ``models/registration/learned`` (methods with the learned
registration), ``models/fusion/network`` (``dnn``) and the registered-pairs network of
``fusion_variants`` (``registered+network``, ``learned+network``): one model per task, the same
at every configuration; a method whose model is missing is skipped and listed. For every configuration (keys of
``configurations``) the same sequences and pose-noise draws are used for every method. Writes:

- ``reports/metrics/twin.json`` — per configuration and method (``ego`` = the ego's own map) and
  scenario kind: recall of critical frames, false-alarm rate, paired recall difference to ``ego``,
  per critical episode the lead time from the first warning within ``twin.horizon_s`` (median,
  mean, paired vs ``ego`` and ``naive``), the share warned before the onset, false alarms (no
  episode within the horizon) per frame and per minute, share of vehicles left out — with
  sequence-bootstrap CIs (:func:`traffictwin.twin.summary.summarise`); ``pose_bias``: the same
  for the kinds ``twin.bias_kinds`` under the persistent pose bias; and ``targets``;
  ``predictive_rule``: the predictive warning's level and confirmation, chosen on the
  ``validation`` split (:mod:`traffictwin.twin.predictive_rule`) before any test sequence is
  evaluated, with every candidate's figures; ``vehicles``: every other vehicle's risk;
- ``reports/twin_eval_frames.csv`` — one row per (configuration, noise model, method, sequence,
  frame) of the ``test`` split; ``reports/twin_vehicle_frames.csv`` — the other vehicles' rows;
- ``reports/plots/twin_timeline.csv`` — DVC plot: THW over time of the timeline sequence;
- ``data/figure_inputs/twin_map.npz`` — the twin at the onset of the timeline sequence (its
  sequence, configuration, method and thresholds in the metadata): plot_data draws
  ``reports/figures/twin_map.png`` and ``twin_timeline.png`` from it and the frames table;
- its run record ``reports/timings/evaluate_twin.json`` (outside DVC): ``step_ms_median`` (median
  wall time of a twin update per configuration, method and scenario kind).

Library: :mod:`traffictwin.twin` (settings: ``twin`` of params.yaml).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from pipelines._common import params, run_stage, setup_logging, stage_timer
from pipelines._figure_inputs import figure_input
from pipelines._inference import pin_torch_threads
from pipelines._paths import (
    REPORTS,
    TWIN_DATA,
    fusion_model_dir,
    metrics_file,
    plot_file,
    registration_model_dir,
)
from traffictwin.fusion.config import (
    NETWORK_MODEL,
    fusion_eval_config,
    grid_config,
    pose_configurations,
)
from traffictwin.io.atomic import write_csv_atomic, write_json_atomic
from traffictwin.twin.data import INF_ARRAYS
from traffictwin.twin.data import TEST_SPLIT as TEST
from traffictwin.twin.data import VALIDATION_SPLIT as VALIDATION

STAGE = "evaluate_twin"
METRICS = metrics_file("twin")
FRAMES = REPORTS / "twin_eval_frames.csv"
VEHICLE_FRAMES = REPORTS / "twin_vehicle_frames.csv"
TIMELINE = plot_file("twin_timeline")
SNAPSHOT = figure_input("twin_map")

log = logging.getLogger("traffictwin.evaluate_twin")


def _csv(frame: pd.DataFrame, path: Path) -> None:
    write_csv_atomic(path, frame, float_format="%.6g")


def method_models(
    cfg: Any, c: str, methods: list[str], grid: Any, cache: dict[str, Any] | None = None
) -> tuple[dict[str, dict[str, Any]], dict[str, str]]:
    """``{method: models}`` available at configuration ``c`` and ``{skipped method: reason}``.

    One model per task serves every configuration and every pose source: the learned
    registration (models/registration/learned) and the one fusion network (models/fusion/network)
    as the combination of every ``*network`` method. ``cache``: models already loaded (filled
    here), so every configuration shares them."""
    from traffictwin.fusion.config import MIXED
    from traffictwin.fusion.model_io import load_fusion_model
    from traffictwin.fusion.registration_io import load_registration_model
    from traffictwin.twin.fuse import TWIN_METHODS

    cache = {} if cache is None else cache

    def load(key: str, loader: Any) -> Any:
        if key not in cache:
            cache[key] = loader()
        return cache[key]

    out: dict[str, dict[str, Any]] = {}
    skipped: dict[str, str] = {}
    for m in methods:
        tm = TWIN_METHODS[m]
        models: dict[str, Any] = {}
        if tm.pose == "learned":
            models["registration"] = load(
                "registration",
                lambda: load_registration_model(
                    registration_model_dir() / "model.ckpt", expected_grid=grid, expected_cfg=MIXED
                ),
            )
        if tm.combine == "network":  # the one fusion network, whatever the pose source
            models["fusion"] = load(
                "fusion",
                lambda: load_fusion_model(
                    fusion_model_dir(NETWORK_MODEL) / "model.ckpt",
                    expected_cfg=MIXED,
                    expected_grid=grid,
                ),
            )
        out[m] = models
    return out, skipped


@dataclass(frozen=True)
class _Pass:
    """What every evaluation pass shares: the grid, the twin's evaluation settings, the classical
    registration's parameters (evaluate_fusion's), its worker processes and the predictive rule
    (:class:`~traffictwin.twin.predictive_rule.PredictiveRule`)."""

    grid: Any
    settings: Any
    reg_params: Any
    workers: int
    rule: Any = None


def _choose_predictive_rule(
    run: _Pass, validation: list[dict[str, Any]], tc: Any, pn: Any, models: dict[str, Any]
) -> tuple[_Pass, dict[str, Any]]:
    """The pass with the predictive rule chosen on the ``validation`` sequences (the headline
    twin at the target configuration's noise ``pn``, per-frame noise; its ``models``), and the
    twin.json entry: every candidate's figures and the one selected. No validation sequence (or
    no model for the headline): the configured level, unconfirmed."""
    from dataclasses import asdict, replace

    from traffictwin.twin.rule_choice import candidate_rules, choose_rule

    candidates = candidate_rules(
        tc.ttc_warn_s, tc.ttc_warn_candidates, tc.ttc_confirm_candidates, tc.reaction_s
    )
    entry: dict[str, Any] = {
        "validation_sequences": len(validation),
        "configuration": tc.target_configuration,
        "method": tc.headline,
        "criterion": "of the candidates whose predictive warning leads THW's (mean, all kinds, "
        "> 0 s), the fewest false alarms beyond THW's (open); ties: the earlier warning",
        "candidates": {},
    }
    rule = candidates[0]
    if validation and tc.headline in models:
        f, _ = _frame_table(run, validation, pn, [tc.headline], models, include_ego=False)
        rule, rows = choose_rule(f, tc.headline, candidates, tc.fps, run.settings)
        entry["candidates"] = {c.key: r for c, r in zip(candidates, rows)}
    entry["selected"] = asdict(rule)
    predict = replace(run.settings.predict, warn_s=rule.warn_s)
    log.info("%s: predictive rule %s (validation: %d sequences)", STAGE, rule, len(validation))
    return replace(run, settings=replace(run.settings, predict=predict), rule=rule), entry


def _frame_table(
    run: _Pass,
    seqs: list[dict[str, Any]],
    pn: Any,
    methods: list[str],
    models: dict[str, Any],
    include_ego: bool = True,
    vehicles: bool = False,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The ego's frame table of ``seqs`` at pose noise ``pn`` and (``vehicles``) every other
    vehicle's: the classical registrations of every sequence at once (one pool of processes),
    then every sequence's twin and risk (another pool; the tables do not depend on its size)."""
    from traffictwin.twin import evaluation as ev

    tp = ev.TwinPass(
        run.grid, (pn.r, pn.alpha), methods, models, run.settings, run.reg_params, run.workers
    )
    reg = (
        ev.classical_registrations(seqs, run.grid, tp.noise, run.reg_params, run.workers)
        if ev.uses_classical(methods, run.settings)
        else [None] * len(seqs)
    )
    tables = ev.evaluate_sequences_tables(seqs, tp, reg, include_ego, vehicles)
    return (
        pd.concat([t.frames for t in tables], ignore_index=True),
        pd.concat([t.vehicles for t in tables], ignore_index=True),
    )


def _pose_bias_frames(
    run: _Pass,
    seqs: list[dict[str, Any]],
    tc: Any,
    pn: Any,
    methods: list[str],
    models: dict[str, Any],
    ego_rows: pd.DataFrame,
) -> pd.DataFrame:
    """The frame table of the sequences of ``twin.bias_kinds`` under the persistent pose bias
    (:func:`traffictwin.twin.noise.pose_noise_z`, ``twin.bias_share``), the same methods; the
    ``ego`` rows (independent of the other vehicles' pose noise) are ``ego_rows`` of the
    per-frame-noise pass, not computed again."""
    from traffictwin.sim.cooperative import KINDS
    from traffictwin.twin import evaluation as ev
    from traffictwin.twin.noise import pose_noise_z

    picked = [
        {**a, "noise_z": pose_noise_z(a["noise_z"], a["bias_z"], "bias", tc.bias_share)}
        for a in seqs
        if KINDS[ev.scalar(a["kind"])] in tc.bias_kinds
    ]
    if not picked:
        raise ValueError(f"'twin.bias_kinds' {list(tc.bias_kinds)}: no sequence of these kinds")
    ids = {ev.scalar(a["sequence"]) for a in picked}
    twin_rows, _ = _frame_table(run, picked, pn, methods, models, include_ego=False)
    f = pd.concat([ego_rows[ego_rows["sequence"].isin(ids)], twin_rows], ignore_index=True)
    return f.sort_values(["sequence", "frame"], kind="stable", ignore_index=True)


def _evaluate_configuration(
    run: _Pass,
    seqs: list[dict[str, Any]],
    tc: Any,
    c: str,
    pn: Any,
    methods: list[str],
    models: dict[str, Any],
) -> tuple[list[pd.DataFrame], pd.DataFrame, dict[str, Any]]:
    """Configuration ``c``'s frame tables (per-frame noise and, for ``twin.bias_kinds``, the
    persistent bias), every other vehicle's frame table (per-frame noise) and its summary entry
    of twin.json."""
    from traffictwin.twin.evaluation import EGO
    from traffictwin.twin.predictive_rule import apply_rule
    from traffictwin.twin.summary import (
        OWN,
        always_warning_reference,
        summarise,
        vehicle_summaries,
    )

    f, v = _frame_table(run, seqs, pn, methods, models, vehicles=True)
    f = apply_rule(f, run.rule)
    f.insert(0, "configuration", c)
    f.insert(1, "noise", "frame")
    entry: dict[str, Any] = {
        "noise": {"r": pn.r, "alpha": pn.alpha},
        "methods": summarise(f, methods, tc.fps, run.settings),
        "always_warns": always_warning_reference(f, methods, tc.fps, run.settings),
        "vehicles": vehicle_summaries(v, methods, tc.fps, run.settings),
    }
    if len(v):
        v.insert(0, "configuration", c)
        v["method"] = v["method"].replace(EGO, OWN)  # the vehicle's own map
    frames = [f]
    if tc.bias_kinds:  # the same sequences' kinds under a persistent (per-sequence) bias
        ego_rows = f[f["method"] == EGO].drop(columns=["configuration", "noise"])
        fb = apply_rule(_pose_bias_frames(run, seqs, tc, pn, methods, models, ego_rows), run.rule)
        fb.insert(0, "configuration", c)
        fb.insert(1, "noise", "bias")
        frames.append(fb)
        entry["pose_bias"] = {
            "bias_share": tc.bias_share,
            "kinds": list(tc.bias_kinds),
            "methods": summarise(fb, methods, tc.fps, run.settings),
        }
    return frames, v, entry


def _figure_inputs(
    run: _Pass,
    table: pd.DataFrame,
    seqs: list[dict[str, Any]],
    tc: Any,
    c_fig: str,
    pn: Any,
    model: Any,
) -> None:
    """What plot_data draws the timeline and the twin map from: the timeline of a typical
    occluded sequence (:data:`TIMELINE`) and the twin at its onset (:data:`SNAPSHOT`, with the
    sequence, configuration ``c_fig``, method and thresholds), per-frame noise."""
    from traffictwin.io.figure_inputs import write_arrays_with_meta
    from traffictwin.twin.evaluation import scalar
    from traffictwin.twin.figure_inputs import pick_timeline_sequence, timeline_table, twin_snapshot

    s = run.settings
    table = table[table["noise"] == "frame"]
    seq = pick_timeline_sequence(table, c_fig, tc.headline, tc.fps, tc.figure.sequence, s.horizon_s)
    _csv(timeline_table(table, c_fig, tc.headline, seq), TIMELINE)
    a = next(x for x in seqs if scalar(x["sequence"]) == seq)
    snap = twin_snapshot(a, run.grid, (pn.r, pn.alpha), tc.headline, model, s, run.reg_params)
    meta = {
        "sequence": seq,
        "configuration": c_fig,
        "method": tc.headline,
        "radius_m": float(pn.r),
        "critical_thw_s": float(s.critical_thw),
        "warn_thw_s": float(s.warn_thw),
    }
    write_arrays_with_meta(SNAPSHOT, snap.arrays(), meta)


def main() -> None:
    from traffictwin.acceptance import for_problem
    from traffictwin.io.jsonio import json_clean
    from traffictwin.io.shards import Dataset
    from traffictwin.twin.config import twin_config
    from traffictwin.twin.summary import step_ms_medians
    from traffictwin.twin.targets import TARGET_NAMES, targets

    setup_logging()
    cfg = params()
    noise = pose_configurations(cfg)
    tc = twin_config(cfg)
    thresholds = for_problem(cfg, "twin", TARGET_NAMES)
    fec = fusion_eval_config(cfg)
    # the classical registration of evaluate_fusion
    run = _Pass(grid_config(cfg), tc.settings(), fec.registration_params, fec.registration_workers)
    with stage_timer(STAGE) as record:
        record["torch_threads"] = pin_torch_threads(cfg)
        ds = Dataset(TWIN_DATA, kind="twin", allow_inf=INF_ARRAYS)
        seqs = [ds.load_shard(i) for i in ds.shard_indices(TEST)]
        validation = [ds.load_shard(i) for i in ds.shard_indices(VALIDATION)]
        frames, vehicle_frames, summary, models_by_cfg, loaded = [], [], {}, {}, {}
        evaluated = {
            c: pn for c, pn in noise.items() if tc.configurations is None or c in tc.configurations
        }
        c_rule = tc.target_configuration if tc.target_configuration in evaluated else None
        rule_models = (
            method_models(cfg, c_rule, [tc.headline], run.grid, loaded)[0] if c_rule else {}
        )
        run, rule_entry = _choose_predictive_rule(
            run, validation if c_rule else [], tc, noise.get(c_rule), rule_models
        )
        for c, pn in evaluated.items():
            models, skipped = method_models(cfg, c, tc.methods, run.grid, loaded)
            models_by_cfg[c] = models
            methods = [m for m in tc.methods if m in models]
            log.info(
                "%s@%s: %d sequences, methods %s (skipped %s)",
                STAGE,
                c,
                len(seqs),
                methods,
                skipped,
            )
            fs, vs, summary[c] = _evaluate_configuration(run, seqs, tc, c, pn, methods, models)
            vehicle_frames.append(vs)
            summary[c]["skipped"] = skipped
            # wall times differ between identical runs: run record only
            record.setdefault("step_ms_median", {})[c] = json_clean(step_ms_medians(fs[0], methods))
            frames += fs
        table = pd.concat(frames, ignore_index=True).drop(columns="step_ms")
        metrics = {
            "headline": tc.headline,
            "strategy": tc.strategy,
            "vehicles": int(table["vehicles"].iloc[0]),
            "sequences": len(seqs),
            "configurations": summary,
            "predictive_rule": rule_entry,
            "targets": targets(summary, tc.headline, tc.target_configuration, thresholds),
        }
        _csv(table, FRAMES)
        _csv(pd.concat(vehicle_frames, ignore_index=True), VEHICLE_FRAMES)
        c_fig = (
            tc.target_configuration if tc.target_configuration in evaluated else list(evaluated)[-1]
        )
        model = models_by_cfg[c_fig].get(tc.headline)
        _figure_inputs(run, table, seqs, tc, c_fig, noise[c_fig], model)
        write_json_atomic(METRICS, json_clean(metrics))
        tg = metrics["targets"]
        checked = [v for v in tg.values() if isinstance(v, dict) and "met" in v]
        log.info(  # one line; every target with its interval is in METRICS
            "%s: twin %s at %s, %d of %d targets met -> %s",
            STAGE,
            tg.get("method"),
            tg.get("configuration"),
            sum(bool(v["met"]) for v in checked),
            len(checked),
            METRICS,
        )


if __name__ == "__main__":
    run_stage(main, STAGE)
