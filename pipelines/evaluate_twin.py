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
  sequence-bootstrap CIs (:func:`traffictwin.twin.evaluation.summarise`); ``pose_bias``: the same
  for the kinds ``twin.bias_kinds`` under the persistent pose bias; and ``targets``;
- ``reports/twin_eval_frames.csv`` — one row per (configuration, noise model, method, sequence,
  frame);
- ``reports/plots/twin_timeline.csv`` — DVC plot: THW over time of the timeline sequence;
- ``reports/figures/twin_map.png``, ``twin_timeline.png``;
- its run record ``reports/timings/evaluate_twin.json`` (outside DVC): ``step_ms_median`` (median
  wall time of a twin update per configuration, method and scenario kind).

Library: :mod:`traffictwin.twin` (settings: ``twin`` of params.yaml).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import pandas as pd

from pipelines._common import params, run_stage, setup_logging, stage_timer
from pipelines._inference import pin_torch_threads
from pipelines._paths import (
    REPORTS,
    TWIN_DATA,
    figure_file,
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

STAGE = "evaluate_twin"
METRICS = metrics_file("twin")
FRAMES = REPORTS / "twin_eval_frames.csv"
TIMELINE = plot_file("twin_timeline")

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
    from traffictwin.fusion.registration_training import load_registration_model
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


def _pose_bias_frames(
    seqs: list[dict[str, Any]],
    tc: Any,
    s: Any,
    grid: Any,
    pn: Any,
    methods: list[str],
    models: dict[str, Any],
    reg_params: Any,
    fec: Any,
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
    reg = (
        ev.classical_registrations(
            picked, grid, (pn.r, pn.alpha), reg_params, fec.registration_workers
        )
        if ev.uses_classical(methods, s)
        else [None] * len(picked)
    )
    ids = {ev.scalar(a["sequence"]) for a in picked}
    twin_rows = [
        ev.evaluate_sequence(
            a,
            grid,
            (pn.r, pn.alpha),
            methods,
            models,
            s,
            reg_params,
            registered=r,
            include_ego=False,
        )
        for a, r in zip(picked, reg)
    ]
    f = pd.concat([ego_rows[ego_rows["sequence"].isin(ids)], *twin_rows], ignore_index=True)
    return f.sort_values(["sequence", "frame"], kind="stable", ignore_index=True)


def main() -> None:
    from traffictwin.io.atomic import save_figure
    from traffictwin.io.jsonio import json_clean
    from traffictwin.io.shards import Dataset
    from traffictwin.twin import evaluation as ev
    from traffictwin.twin.config import twin_config
    from traffictwin.twin.figures import (
        pick_timeline_sequence,
        timeline_figure,
        timeline_table,
        twin_map_figure,
    )

    setup_logging()
    cfg = params()
    grid = grid_config(cfg)
    noise = pose_configurations(cfg)
    tc = twin_config(cfg)
    s = tc.settings()
    fec = fusion_eval_config(cfg)
    reg_params = fec.registration_params  # the classical registration of evaluate_fusion
    with stage_timer(STAGE) as record:
        record["torch_threads"] = pin_torch_threads(cfg)
        ds = Dataset(TWIN_DATA, kind="twin", allow_inf=INF_ARRAYS)
        seqs = [ds.load_shard(i) for i in ds.shard_indices()]
        frames, summary = [], {}
        models_by_cfg: dict[str, Any] = {}
        loaded: dict[str, Any] = {}
        evaluated = {
            c: pn for c, pn in noise.items() if tc.configurations is None or c in tc.configurations
        }
        for c, pn in evaluated.items():
            models, skipped = method_models(cfg, c, tc.methods, grid, loaded)
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
            # the classical registrations of every sequence at once: one pool of processes
            reg = (
                ev.classical_registrations(
                    seqs, grid, (pn.r, pn.alpha), reg_params, fec.registration_workers
                )
                if ev.uses_classical(methods, s)
                else [None] * len(seqs)
            )
            f = pd.concat(
                [
                    ev.evaluate_sequence(
                        a, grid, (pn.r, pn.alpha), methods, models, s, reg_params, registered=r
                    )
                    for a, r in zip(seqs, reg)
                ],
                ignore_index=True,
            )
            f.insert(0, "configuration", c)
            f.insert(1, "noise", "frame")
            frames.append(f)
            summary[c] = {
                "noise": {"r": pn.r, "alpha": pn.alpha},
                "methods": ev.summarise(f, methods, tc.fps, s),
                "skipped": skipped,
            }
            # wall times differ between identical runs: run record only
            record.setdefault("step_ms_median", {})[c] = json_clean(ev.step_ms_medians(f, methods))
            if tc.bias_kinds:  # the same sequences' kinds under a persistent (per-sequence) bias
                ego_rows = f[f["method"] == ev.EGO].drop(columns=["configuration", "noise"])
                fb = _pose_bias_frames(
                    seqs, tc, s, grid, pn, methods, models, reg_params, fec, ego_rows
                )
                fb.insert(0, "configuration", c)
                fb.insert(1, "noise", "bias")
                frames.append(fb)
                summary[c]["pose_bias"] = {
                    "bias_share": tc.bias_share,
                    "kinds": list(tc.bias_kinds),
                    "methods": ev.summarise(fb, methods, tc.fps, s),
                }
        table = pd.concat(frames, ignore_index=True).drop(columns="step_ms")
        metrics = {
            "headline": tc.headline,
            "strategy": tc.strategy,
            "vehicles": int(table["vehicles"].iloc[0]),
            "sequences": len(seqs),
            "configurations": summary,
            "targets": ev.targets(summary, tc.headline, tc.target_configuration),
        }
        _csv(table, FRAMES)
        table = table[table["noise"] == "frame"]  # the figures: per-frame noise
        c_fig = (
            tc.target_configuration if tc.target_configuration in evaluated else list(evaluated)[-1]
        )
        seq = pick_timeline_sequence(
            table, c_fig, tc.headline, tc.fps, tc.figure.sequence, s.horizon_s
        )
        _csv(timeline_table(table, c_fig, tc.headline, seq), TIMELINE)
        save_figure(
            timeline_figure(table, c_fig, tc.headline, seq, s.critical_thw, s.warn_thw),
            figure_file("twin_timeline"),
        )
        a = next(x for x in seqs if ev.scalar(x["sequence"]) == seq)
        pn = noise[c_fig]
        save_figure(
            twin_map_figure(
                a,
                grid,
                (pn.r, pn.alpha),
                tc.headline,
                models_by_cfg[c_fig].get(tc.headline),
                s,
                c_fig,
                reg_params,
            ),
            figure_file("twin_map"),
        )
        write_json_atomic(METRICS, json_clean(metrics))
        log.info("%s: targets %s", STAGE, metrics["targets"])


if __name__ == "__main__":
    run_stage(main, STAGE)
