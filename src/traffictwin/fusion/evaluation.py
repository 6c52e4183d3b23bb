"""Fusion evaluation (paper V-A, Figs. 4–7): every registered method on every configuration's test set.

The stage ``evaluate_fusion`` reads params and paths and writes the outputs; everything in
between is here, with paths and settings as explicit arguments:

- :func:`load_test_sets` / :func:`load_raw_pairs` — the same pair ids (and so the same noise
  draws) for every configuration and method;
- :func:`evaluate_method` — per-sample metrics of one registered method
  (:data:`traffictwin.fusion.methods.METHODS`) on a :class:`~traffictwin.fusion.methods.FusionInput`;
- :func:`evaluate` — every method × configuration, each network on every configuration (the
  cross table), pose-error bins: returns an :class:`Evaluation` (the ``fusion.json`` dict and the
  samples table);
- :func:`plot_tables`, :func:`figures`, :func:`qualitative_panels` — DVC plot data and figures;
- :func:`json_clean`, :func:`mlflow_metrics` — JSON-safe metrics, the flat per-network numbers.

Metrics layout: ``test.<cfg>.<method>.<metric>``, ``cross.dnn-<net>.<cfg>.<metric>``,
``bins.{translation,rotation}.<method>.<bin>.<metric>``, ``runtime_ms_per_pair.<method>``,
``n_pairs.{per_config,registered,cross}``.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from traffictwin.fusion.config import FusionEvalConfig, PoseNoise
from traffictwin.fusion.methods import METHODS, FusionInput, FusionMethod
from traffictwin.fusion.metrics import UncertaintyAUROC, aggregate
from traffictwin.grid import GridSpec
from traffictwin.io.shards import Dataset, DatasetError

__all__ = [
    "EvalSettings",
    "Evaluation",
    "SUMMARY_KEYS",
    "CROSS_KEYS",
    "BIN_KEYS",
    "FIGURE_METHODS",
    "evenly_spaced",
    "load_test_sets",
    "load_raw_pairs",
    "evaluate_method",
    "evaluate",
    "pose_bins",
    "qualitative_panels",
    "plot_tables",
    "figures",
    "json_clean",
    "mlflow_metrics",
]

# precision / recall / Dice of both classes, pooled over samples
CLASS_SCORE_KEYS = tuple(
    f"{m}_{c}" for c in ("occ", "free") for m in ("precision", "recall", "dice")
)
SUMMARY_KEYS = (
    "n",
    *(f"kld_fo_{s}" for s in ("mean", "median", "q25", "q75")),
    "kld_fou_mean",
    "kld_fou_median",
    *CLASS_SCORE_KEYS,
    "dice_occ_sample_mean",
    "dice_free_sample_mean",
    "u_mean",
    "u_mean_known",
)
CROSS_KEYS = (
    "n",
    "kld_fo_mean",
    "kld_fou_mean",
    "dice_occ",
    "dice_free",
    "precision_occ",
    "recall_occ",
)
BIN_KEYS = ("n", "kld_fo_mean", "kld_fo_median", "dice_occ", "dice_free")
SCORE_KEYS = (*CLASS_SCORE_KEYS, "kld_fo_mean")  # the columns of fusion_scores.csv per method
# the method order of the score plots / fusion_scores.csv and the methods of the KLD box plot
SCORE_METHODS = ("dnn", "naive", "registered", "naive-yager", "naive-cautious", "ego")
FIGURE_METHODS = ("naive", "registered", "dnn")
NETWORK = "dnn"  # the network method; its cross entries are "dnn-<net>"

log = logging.getLogger("traffictwin.evaluate_fusion")


@dataclass(frozen=True)
class EvalSettings:
    """How per-sample metrics are computed (units in the names)."""

    batch_size: int = 8
    kld_eps: float = 1e-7
    auroc_bins: int = 4096
    success_trans_m: float = 0.5
    success_rot_deg: float = 1.0

    @classmethod
    def from_config(cls, c: FusionEvalConfig) -> EvalSettings:
        return cls(c.batch_size, c.kld_eps, c.auroc_bins, c.success_trans_m, c.success_rot_deg)


@dataclass
class Evaluation:
    """Result of :func:`evaluate`: ``metrics`` (the fusion.json dict, before :func:`json_clean`),
    ``samples`` (one row per configuration × method × pair), ``bins`` (pose-error bin table),
    ``data`` / ``raw`` (the evaluated arrays per configuration / raw pairs) and ``models``."""

    metrics: dict[str, Any]
    samples: pd.DataFrame
    bins: pd.DataFrame
    data: dict[str, dict[str, np.ndarray]]
    raw: dict[str, np.ndarray]
    models: dict[str, Any]


# -- data ----------------------------------------------------------------------------------------
def evenly_spaced(n: int, k: int | None) -> np.ndarray:
    """``k`` indices spread evenly over ``range(n)`` (all when ``k`` is None or ≥ n)."""
    if k is None or k >= n:
        return np.arange(n)
    return np.unique(np.round(np.linspace(0, n - 1, k)).astype(np.int64))


def load_test_sets(
    roots: Mapping[str, str | Path], split: str, max_pairs: int | None
) -> tuple[dict[str, dict[str, np.ndarray]], np.ndarray]:
    """Each configuration's ``split`` arrays (``roots[cfg]`` = its prealigned dataset) restricted to
    the same pair ids: ``max_pairs`` of the pair ids common to all configurations, spread evenly
    over them (so over scenarios/templates)."""
    raw = {}
    for c, root in roots.items():
        ds = Dataset(root, kind="prealigned")
        raw[c] = ds.load_all(split)
        for key in ("inputs", "label", "noise", "rel_pose_true", "rel_pose_noisy", "pair_id"):
            if key not in raw[c]:
                raise DatasetError(f"{ds.root}: array '{key}' missing in split '{split}'")
    common = np.array(
        sorted(set.intersection(*(set(raw[c]["pair_id"].tolist()) for c in roots))),
        dtype=np.int64,
    )
    if not len(common):
        raise DatasetError(
            f"{', '.join(str(r) for r in roots.values())}: no pair id common to all '{split}' splits"
        )
    chosen = common[evenly_spaced(len(common), max_pairs)]
    out = {}
    for c in roots:
        pid = raw[c]["pair_id"]
        index = {int(pid[i]): i for i in range(len(pid) - 1, -1, -1)}  # the first draw wins
        idx = np.array([index[int(p)] for p in chosen], dtype=np.int64)
        out[c] = {k: v[idx] for k, v in raw[c].items()}
    return out, chosen


def load_raw_pairs(root: str | Path, pair_ids: np.ndarray, split: str) -> dict[str, np.ndarray]:
    """``map1``, ``map2``, ``label``, ``pose1``, ``pose2`` of the fusion dataset ``root`` for
    ``pair_ids`` (in that order)."""
    ds = Dataset(root, kind="fusion")
    keys = ("map1", "map2", "label", "pose1", "pose2", "pair_id")
    arrays = ds.load_all(split, keys=keys)
    index = {int(p): i for i, p in enumerate(arrays["pair_id"])}
    missing = [int(p) for p in pair_ids if int(p) not in index]
    if missing:
        raise DatasetError(
            f"{ds.root}: pair ids {missing[:5]} of the prealigned data missing in split '{split}' (stale data?)"
        )
    idx = np.array([index[int(p)] for p in pair_ids], dtype=np.int64)
    return {k: arrays[k][idx] for k in keys}


# -- one method ----------------------------------------------------------------------------------
def _batches(n: int, size: int):
    for s in range(0, n, max(1, size)):
        yield slice(s, min(n, s + size))


def evaluate_method(
    method: FusionMethod | str, x: FusionInput, label: np.ndarray, settings: EvalSettings
) -> tuple[pd.DataFrame, UncertaintyAUROC]:
    """Per-sample metrics of ``method`` on the pairs ``x`` against ``label`` (N, 2, H, W).

    Returns one row per pair (:func:`~traffictwin.fusion.metrics.per_sample_metrics`, ``ms`` = wall
    time per pair: the method's own per-pair timing if it has one, else its batch's time / size,
    plus the method's diagnostic ``columns``) and the streaming u-AUROC of the whole set.
    """
    from traffictwin.fusion.metrics import per_sample_metrics

    method = METHODS[method] if isinstance(method, str) else method
    auroc = UncertaintyAUROC(bins=settings.auroc_bins)
    parts, extra, seconds = [], [], []
    for sl in _batches(len(label), settings.batch_size):
        t0 = time.perf_counter()
        batch = x.take(sl)
        fused = method(batch)
        ms = 1000.0 * (time.perf_counter() - t0) / (sl.stop - sl.start)
        pred = fused.masses
        if pred.shape != label[sl].shape:
            raise ValueError(
                f"{method.name}: prediction shape {pred.shape} != label shape {label[sl].shape} "
                f"for samples {sl.start}:{sl.stop}"
            )
        auroc.update(label[sl], pred)
        frame = pd.DataFrame(per_sample_metrics(label[sl], pred, settings.kld_eps))
        frame["ms"] = ms
        parts.append(frame)
        if method.columns is not None:
            extra.append(method.columns(fused, batch, settings))
        if fused.seconds is not None:
            seconds.append(fused.seconds)
    frame = pd.concat(parts, ignore_index=True)
    for k in extra[0] if extra else ():
        frame[k] = np.concatenate([e[k] for e in extra])
    if seconds:
        frame["ms"] = 1000.0 * np.concatenate(seconds)
    return frame, auroc


def _summary(frame: pd.DataFrame) -> dict[str, float]:
    agg = aggregate({k: frame[k].to_numpy() for k in frame.columns})
    out = {k: agg[k] for k in SUMMARY_KEYS if k in agg}
    out["ms_per_pair"] = float(frame["ms"].mean())
    return out


def _tag(
    frame: pd.DataFrame,
    cfg: str,
    method: str,
    d: dict[str, np.ndarray],
    idx: np.ndarray,
    network: str = "",
) -> pd.DataFrame:
    """The samples-table rows: configuration, method, network, pair id and the noise drawn."""
    frame = frame.copy()
    nz = d["noise"][idx]
    frame.insert(0, "pair_id", d["pair_id"][idx])
    frame.insert(0, "network", network)
    frame.insert(0, "method", method)
    frame.insert(0, "config", cfg)
    frame["noise_dx"], frame["noise_dy"], frame["noise_dyaw"] = nz[:, 0], nz[:, 1], nz[:, 2]
    frame["trans_err_m"] = np.hypot(nz[:, 0], nz[:, 1])
    frame["rot_err_deg"] = np.degrees(np.abs(nz[:, 2]))
    return frame


# -- all methods ---------------------------------------------------------------------------------
def pose_bins(
    frame: pd.DataFrame, trans_bins_m: Sequence[float], rot_bins_deg: Sequence[float]
) -> tuple[dict[str, Any], pd.DataFrame]:
    """Metrics per method and bin of the drawn translation / rotation error (dict and table)."""
    from traffictwin.fusion.metrics import pose_error_bins

    noise = frame[["noise_dx", "noise_dy", "noise_dyaw"]].to_numpy()
    tb, rb, tl, rl = pose_error_bins(noise, trans_bins_m, rot_bins_deg)
    frame = frame.assign(trans_bin=[tl[i] for i in tb], rot_bin=[rl[i] for i in rb])
    out: dict[str, Any] = {"translation": {}, "rotation": {}}
    rows = []
    for axis, col, labels in (("translation", "trans_bin", tl), ("rotation", "rot_bin", rl)):
        for meth, g in frame.groupby("method", sort=False):
            out[axis][meth] = {}
            for lab in labels:
                sub = g[g[col] == lab]
                if len(sub):
                    agg = aggregate({k: sub[k].to_numpy() for k in sub.columns})
                    out[axis][meth][lab] = {k: agg[k] for k in BIN_KEYS if k in agg}
                    rows.append({"axis": axis, "bin": lab, "method": meth, **out[axis][meth][lab]})
    return out, pd.DataFrame(rows)


def evaluate(
    data: dict[str, dict[str, np.ndarray]],
    raw: dict[str, np.ndarray],
    models: dict[str, Any],
    grid: GridSpec,
    cfg: FusionEvalConfig,
) -> Evaluation:
    """Every registered method on every configuration of ``data`` (from :func:`load_test_sets`,
    in configuration order), ``raw`` its raw pairs (:func:`load_raw_pairs`), ``models[cfg]``
    each configuration's network. Slow methods run on ``cfg.registered_max_pairs`` pairs, the
    networks on other configurations' pairs (cross table) on ``cfg.cross_max_pairs``."""
    configs = list(data)
    es = EvalSettings.from_config(cfg)
    n = len(next(iter(data.values()))["pair_id"])
    all_idx = np.arange(n)
    reg_idx = evenly_spaced(n, cfg.registered_max_pairs)
    cross_idx = evenly_spaced(n, cfg.cross_max_pairs)
    log.info(
        "evaluating %d pairs per configuration (%d registered, %d cross) on %s",
        n,
        len(reg_idx),
        len(cross_idx),
        configs,
    )
    frames: list[pd.DataFrame] = []
    metrics: dict[str, Any] = {"test": {}, "cross": {f"{NETWORK}-{c}": {} for c in configs}}
    for c in configs:
        d = data[c]
        metrics["test"][c] = {}
        for name, method in METHODS.items():
            base = FusionInput(
                inputs=d["inputs"],
                map1=raw["map1"],
                map2=raw["map2"],
                rel_pose_noisy=d["rel_pose_noisy"],
                rel_pose_true=d["rel_pose_true"],
                grid=grid,
                batch_size=cfg.batch_size,
                registration=cfg.registration_params,
            )
            # with a model: each configuration's network on this configuration (own: all pairs)
            nets = configs if "model" in method.needs else [None]
            for net in nets:
                own = net in (None, c)
                idx = reg_idx if method.slow else (all_idx if own else cross_idx)
                x = base.take(idx)
                x.model = models[net] if net is not None else None
                f, au = evaluate_method(method, x, d["label"][idx], es)
                label = name if own else f"{name}-{net}"
                frames.append(_tag(f, c, label, d, idx, network=net or ""))
                if net is not None:
                    agg = aggregate({k: f[k].to_numpy() for k in f.columns})
                    metrics["cross"][f"{name}-{net}"][c] = {k: agg[k] for k in CROSS_KEYS} | {
                        "u_auroc": au.value()
                    }
                if own:
                    extra = method.summary(f, es) if method.summary else {}
                    metrics["test"][c][name] = {**_summary(f), "u_auroc": au.value(), **extra}
        t = metrics["test"][c]
        log.info(
            "config %s: KLD naive %.4f, network %.4f, registered %.4f (success %.0f %%)",
            c,
            t["naive"]["kld_fo_mean"],
            t[NETWORK]["kld_fo_mean"],
            t["registered"]["kld_fo_mean"],
            100 * t["registered"]["success_rate"],
        )
    samples = pd.concat(frames, ignore_index=True)
    main = samples[~samples["method"].str.startswith(f"{NETWORK}-")]
    metrics["bins"], bins_table = pose_bins(main, cfg.trans_bins_m, cfg.rot_bins_deg)
    metrics["runtime_ms_per_pair"] = {
        m: float(g["ms"].mean()) for m, g in main.groupby("method", sort=False)
    }
    metrics["n_pairs"] = {
        "per_config": int(n),
        "registered": int(len(reg_idx)),
        "cross": int(len(cross_idx)),
    }
    return Evaluation(metrics, samples, bins_table, data, raw, models)


# -- outputs -------------------------------------------------------------------------------------
def json_clean(obj: Any) -> Any:
    """JSON-safe: NaN/inf → None (DVC and json both choke on NaN), numpy scalars → Python."""
    if isinstance(obj, dict):
        return {str(k): json_clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_clean(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def qualitative_panels(
    ev: Evaluation,
    noise: Mapping[str, PoseNoise],
    grid: GridSpec,
    pair: int,
    fraction: float,
) -> dict[str, list[np.ndarray]]:
    """Fig. 4 panels (label / naive / network, one per configuration) of evaluated pair ``pair``:
    map 2 prealigned with a pose error of ``fraction``·(r, r, α) of each configuration."""
    from traffictwin.config import ConfigError
    from traffictwin.evidential.dempster import dempster
    from traffictwin.fusion.model_io import predict_masses
    from traffictwin.fusion.pairs import prealign

    if pair >= len(ev.raw["map1"]):
        raise ConfigError(
            f"params.yaml: 'evaluation.fusion.qualitative_pair' = {pair} but only "
            f"{len(ev.raw['map1'])} pairs are evaluated"
        )
    m1, m2 = ev.raw["map1"][pair], ev.raw["map2"][pair]
    pose1, pose2 = ev.raw["pose1"][pair], ev.raw["pose2"][pair]
    k = fraction
    rows: dict[str, list[np.ndarray]] = {"label": [], "naive": [], "network": []}
    for c in ev.data:
        r, alpha = noise[c].r, noise[c].alpha
        err = np.array([k * r, k * r, np.radians(k * alpha)])
        warped, _ = prealign(m2, pose1, pose2, grid, noise=err)
        inputs = np.concatenate([m1, warped])[None].astype(np.float32)
        rows["label"].append(ev.raw["label"][pair])
        rows["naive"].append(np.asarray(dempster(m1, warped)))
        rows["network"].append(predict_masses(ev.models[c], inputs, 1)[0][0])
    return rows


def plot_tables(ev: Evaluation, noise: Mapping[str, PoseNoise]) -> dict[str, pd.DataFrame]:
    """DVC plot data: ``fusion_kld`` (per pair), ``fusion_scores`` (per configuration and method),
    ``fusion_pose_bins`` (per bin)."""
    samples = ev.samples
    main = samples[~samples["method"].str.startswith(f"{NETWORK}-")]
    score_rows = []
    for c in ev.data:
        row: dict[str, Any] = {
            "config": c,
            "noise_r_m": noise[c].r,
            "noise_alpha_deg": noise[c].alpha,
        }
        for m in SCORE_METHODS:
            for key in SCORE_KEYS:
                row[f"{m}_{key}"] = ev.metrics["test"][c][m].get(key)
        score_rows.append(row)
    return {
        "fusion_kld": main[
            ["config", "method", "pair_id", "kld_fo", "kld_fou", "trans_err_m", "rot_err_deg"]
        ],
        "fusion_scores": pd.DataFrame(score_rows),
        "fusion_pose_bins": ev.bins,
    }


def figures(
    ev: Evaluation,
    noise: Mapping[str, PoseNoise],
    grid: GridSpec,
    pair: int,
    fraction: float,
) -> dict[str, Any]:
    """The evaluation's matplotlib figures by file stem: ``fusion_kld_boxplot`` (Fig. 5),
    ``fusion_scores_occupied`` / ``fusion_scores_free`` (Figs. 6, 7), ``fusion_qualitative`` (Fig. 4)."""
    from traffictwin.fusion.figures import kld_boxplot, qualitative_grid, scores_plot

    configs = list(ev.data)
    samples = ev.samples
    main = samples[~samples["method"].str.startswith(f"{NETWORK}-")]
    n = ev.metrics["n_pairs"]
    kvals = {
        m: {c: main[(main.method == m) & (main.config == c)]["kld_fo"].to_numpy() for c in configs}
        for m in FIGURE_METHODS
    }
    scores = {m: {c: ev.metrics["test"][c][m] for c in configs} for m in SCORE_METHODS}
    return {
        "fusion_kld_boxplot": kld_boxplot(
            kvals,
            configs,
            list(FIGURE_METHODS),
            title=f"KLD per configuration (test set, {n['per_config']} pairs; registered on "
            f"{n['registered']})",
        ),
        "fusion_scores_occupied": scores_plot(scores, configs, list(SCORE_METHODS), "occ"),
        "fusion_scores_free": scores_plot(scores, configs, list(SCORE_METHODS), "free"),
        "fusion_qualitative": qualitative_grid(
            qualitative_panels(ev, noise, grid, pair, fraction),
            configs,
            title=f"pair {int(ev.data[configs[0]]['pair_id'][pair])}: pose error = "
            f"{fraction:.0%} of (r, r, α); red = m_O, green = m_F, black = unknown",
        ),
    }


def mlflow_metrics(metrics: Mapping[str, Any], cfg: str) -> dict[str, float]:
    """The flat numbers of configuration ``cfg``'s network run: ``test/<k>`` (its own network),
    ``test_<method>/<k>`` (the other methods), ``cross_<other>/<k>`` (the network on other
    configurations); finite values only."""
    flat: dict[str, float] = {}
    for meth, vals in metrics["test"][cfg].items():
        prefix = "test" if meth == NETWORK else f"test_{meth}"
        flat.update({f"{prefix}/{k}": v for k, v in vals.items()})
    for other, vals in metrics["cross"][f"{NETWORK}-{cfg}"].items():
        flat.update({f"cross_{other}/{k}": v for k, v in vals.items()})
    return {k: float(v) for k, v in flat.items() if v is not None and math.isfinite(float(v))}
