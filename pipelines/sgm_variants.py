"""Stage sgm_variants: SGM variants scored on validation pairs, one chosen by a rule fixed
beforehand, and the chosen one against the configured matcher on the test split.

Usage: ``python -m pipelines.sgm_variants``. Reads ``data/risk``, ``data/disparity`` (the
configured matcher's disparity of the same pairs) and params.yaml ``risk_data.sgm`` (the configured
matcher), ``evaluation.stereo.sgm_variants`` (``grid``: the settings to vary,
:func:`traffictwin.stereo.variants.variant_grid`; ``max_frames``: evenly spaced fault-free
validation frames) and ``evaluation.stereo.n_boot``. Writes ``reports/metrics/sgm_variants.json``:

- ``validation``: per variant (:func:`~traffictwin.stereo.variants.variant_name`) its settings and,
  on its own estimated pixels of the validation frames, EPE (px), bad-1, density and the relative
  range error on the object pixels at the critical distances (median, p90, share estimated);
- ``choice``: the chosen variant, the rule (:mod:`traffictwin.stereo.variants`) and whether it is
  the configured matcher;
- ``test``: on every fault-free test frame, the configured matcher (``configured``, from
  data/disparity) and the chosen one (``chosen``) on both pixel masks with sequence-bootstrap
  intervals and the paired difference chosen − configured (:mod:`traffictwin.stereo.evaluation`);
  only a ``why`` when the chosen variant is the configured matcher.

Seconds per frame of each variant go to the run record (they vary between identical runs).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from traffictwin.config import ConfigError, get, typed
from traffictwin.io.atomic import write_json_atomic
from traffictwin.io.shards import Dataset, DatasetError, derived_dataset
from traffictwin.risk.config import RiskDataConfig
from traffictwin.risk.stereo_shards import load_stereo_shard
from traffictwin.stereo.evaluation import critical_objects, evaluate, frame_sums, statistics
from traffictwin.stereo.sgm import SgmParams, disparity_frames
from traffictwin.stereo.variants import (
    CRITERION,
    GUARD,
    choose_variant,
    settings,
    variant_grid,
    variant_name,
)

from ._common import params, run_stage, setup_logging, stage_timer
from ._paths import DISPARITY, PARAMS, RISK_DATA, metrics_file

if TYPE_CHECKING:
    import pandas as pd

STAGE = "sgm_variants"
#: the validation figures of a variant (its own pixels)
FIGURES = ("epe", "bad1", "density", CRITERION, "crit_obj_relerr_p90", GUARD)


def _camera(ds: Dataset) -> dict[str, float]:
    cam = ds.manifest.get("camera") or {}
    need = {"fx", "baseline", "cy", "fy", "mount_height"}
    if not need <= set(cam):
        raise DatasetError(
            f"{Path(ds.root) / 'manifest.json'}: 'camera' lacks {sorted(need - set(cam))}"
        )
    return {k: float(cam[k]) for k in need}


def _select(frames: pd.DataFrame, split: str, limit: int = 0) -> pd.DataFrame:
    """The fault-free ``split`` frames in shard order, ``limit`` evenly spaced (0 = all)."""
    sel = frames[(frames.split == split) & (frames.fault == "none")].sort_values(["shard", "idx"])
    if 0 < limit < len(sel):
        sel = sel.iloc[np.unique(np.linspace(0, len(sel) - 1, limit).round().astype(int))]
    return sel


def _load(ds: Dataset, sel: pd.DataFrame, extra: Dataset | None = None) -> dict[str, np.ndarray]:
    """``left``, ``right``, ``disp_gt`` (and ``disp_sgm`` from ``extra``) of the rows ``sel``."""
    parts: dict[str, list[np.ndarray]] = {"left": [], "right": [], "disp_gt": [], "disp_sgm": []}
    for shard, g in sel.groupby("shard", sort=True):
        sh = load_stereo_shard(ds, int(shard), ("left", "right", "disp_gt"))
        idx = g.idx.to_numpy()
        for k in ("left", "right", "disp_gt"):
            parts[k].append(np.asarray(sh[k])[idx])
        if extra is not None:
            parts["disp_sgm"].append(np.asarray(extra.load_shard(int(shard))["disp_sgm"])[idx])
    return {k: np.concatenate(v) for k, v in parts.items() if v}


def _own_figures(disp: np.ndarray, gt: np.ndarray, fx_b: float, obj: np.ndarray) -> dict:
    """:data:`FIGURES` of one matcher's maps over all frames (its own estimated pixels)."""
    sums = frame_sums({"m": disp}, gt, fx_b, obj)["m/own"]
    st = statistics(sums, np.ones(len(gt)))
    return {k: (None if not np.isfinite(st[k]) else st[k]) for k in FIGURES}


def _test_comparison(
    ds: Dataset,
    frames: pd.DataFrame,
    best: SgmParams,
    configured_disp: Dataset,
    cam: dict[str, float],
    n_boot: int,
    src: Path,
) -> dict[str, Any]:
    """The chosen variant ``best`` against the configured matcher's data/disparity on the
    fault-free test frames (:func:`evaluate`, paired chosen - configured; None where not finite)."""
    fx_b = cam["fx"] * cam["baseline"]
    test_rows = _select(frames, "test")
    if test_rows.empty:
        raise DatasetError(f"{src}: no fault-free test frames to compare on")
    acc, seqs = [], []
    for _, g in test_rows.groupby("shard", sort=True):  # a shard at a time: bounded memory
        t = _load(ds, g, configured_disp)
        d, _ = disparity_frames(t["left"], t["right"], best)
        o = critical_objects(t["disp_gt"], fx_b, cam)
        acc.append(frame_sums({"configured": t["disp_sgm"], "chosen": d}, t["disp_gt"], fx_b, o))
        seqs.append(g.scenario.to_numpy())
    sums = {k: {f: np.concatenate([a[k][f] for a in acc]) for f in acc[0][k]} for k in acc[0]}
    m = evaluate(sums, np.concatenate(seqs), n_boot, pairs=(("chosen", "configured"),))
    return {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in m.items()}


def run(
    sgm: SgmParams,
    grid: dict[str, list[Any]],
    max_frames: int,
    n_boot: int,
    src: Path = RISK_DATA,
    disparity: Path = DISPARITY,
    record: dict | None = None,
) -> dict[str, Any]:
    """Score the variants on validation, choose, compare on test; returns the metrics."""
    log = setup_logging()
    if not (Path(src) / "manifest.json").exists():
        raise DatasetError(f"{src}: no manifest.json (run `dvc repro generate_risk` first)")
    ds = Dataset(src, kind="risk")  # verifies every shard's SHA-256
    configured_disp = derived_dataset(disparity, "disparity", ds, "data/risk", "disparity")
    variants = variant_grid(sgm, grid)
    cam = _camera(ds)
    fx_b = cam["fx"] * cam["baseline"]
    frames = ds.table("frames.csv")
    val_rows = _select(frames, "val", max_frames)
    if val_rows.empty:
        raise DatasetError(f"{src}: no fault-free validation frames to score the variants on")
    val = _load(ds, val_rows)
    for v in variants:  # before any matching
        v.check_width(val["left"].shape[2], what=f"sgm variant {variant_name(v)}")
    obj = critical_objects(val["disp_gt"], fx_b, cam)
    figures: dict[str, dict] = {}
    secs: dict[str, float] = {}
    for v in variants:
        t0 = time.perf_counter()
        d, _ = disparity_frames(val["left"], val["right"], v)
        secs[variant_name(v)] = (time.perf_counter() - t0) / len(d)
        figures[variant_name(v)] = {
            "settings": settings(v),
            **_own_figures(d, val["disp_gt"], fx_b, obj),
        }
    configured = variant_name(sgm)
    chosen, why = choose_variant(figures, configured)
    out: dict[str, Any] = {
        "validation": {"frames": int(len(val_rows)), "variants": figures},
        "choice": {
            "chosen": chosen,
            "configured": configured,
            "is_configured": chosen == configured,
            "rule": why,
            "settings": figures[chosen]["settings"],
        },
    }
    if chosen == configured:
        out["test"] = {"why": "the chosen variant is the configured matcher"}
    else:
        best = next(v for v in variants if variant_name(v) == chosen)
        out["test"] = _test_comparison(ds, frames, best, configured_disp, cam, n_boot, src)
    if record is not None:  # timings vary between identical runs: run record only
        record["ms_per_frame"] = {k: round(1000.0 * s, 3) for k, s in secs.items()}
    f = figures[chosen]
    log.info(
        "%s: %d variants on %d validation frames; chosen %s (%s): critical objects median %.2f %% "
        "(configured %.2f %%)",
        STAGE,
        len(variants),
        len(val_rows),
        chosen,
        "the configured matcher" if chosen == configured else "a variant",
        100 * (f[CRITERION] or float("nan")),
        100 * (figures[configured][CRITERION] or float("nan")),
    )
    return out


def variant_settings(p: Any) -> tuple[SgmParams, dict[str, list[Any]], int, int]:
    """``(configured matcher, grid, max_frames, n_boot)`` from params ``p``, validated (every
    variant of the grid builds); ConfigError naming the key."""
    rd = typed(p.get("risk_data"), RiskDataConfig, key="risk_data")
    key = "evaluation.stereo.sgm_variants"
    grid = dict(get(p, f"{key}.grid", dict))
    max_frames = get(p, f"{key}.max_frames", int, min=1)
    n_boot = get(p, "evaluation.stereo.n_boot", int, min=10)
    try:
        variant_grid(rd.sgm, grid)
    except ValueError as exc:
        raise ConfigError(f"{PARAMS.name}: '{key}.grid': {exc}") from None
    return rd.sgm, grid, max_frames, n_boot


def main() -> None:
    sgm, grid, max_frames, n_boot = variant_settings(params())  # before anything runs
    with stage_timer(STAGE) as record:
        metrics = run(sgm, grid, max_frames, n_boot, record=record)
        write_json_atomic(metrics_file(STAGE), metrics)


if __name__ == "__main__":
    run_stage(main, STAGE)
