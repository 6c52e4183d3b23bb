"""One registered method on a set of pairs: per-pair metrics (wall time ``ms`` per pair), the
samples-table rows and the aggregates of one row (its summary, its cross-table entry, its numbers
per pose-error bin)."""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from traffictwin.evidential.masses import unknown_mass
from traffictwin.fusion.evaluation.keys import BIN_KEYS, CROSS_KEYS, SUMMARY_KEYS, EvalSettings
from traffictwin.fusion.methods import METHODS, FusionInput, FusionMethod
from traffictwin.fusion.metrics import UncertaintyAUROC, aggregate

if TYPE_CHECKING:  # pandas loads where a table is built: check_params imports this package
    import pandas as pd


def _batches(n: int, size: int):
    for s in range(0, n, max(1, size)):
        yield slice(s, min(n, s + size))


def evaluate_method(
    method: FusionMethod | str, x: FusionInput, label: np.ndarray, settings: EvalSettings
) -> tuple[pd.DataFrame, UncertaintyAUROC]:
    """Per-sample metrics of ``method`` on the pairs ``x`` against ``label`` (N, 2, H, W).

    Returns one row per pair (:func:`~traffictwin.fusion.metrics.per_sample_metrics`, ``ms`` = wall
    time per pair: the method's own per-pair timing if it has one, else its batch's time / size,
    plus the method's diagnostic ``columns``) and the streaming u-AUROC of the whole set (with the
    per-pair histograms of u, :meth:`~traffictwin.fusion.metrics.UncertaintyAUROC.sample_histograms`).
    """
    import pandas as pd

    from traffictwin.fusion.metrics import per_sample_metrics

    method = METHODS[method] if isinstance(method, str) else method
    auroc = UncertaintyAUROC(bins=settings.auroc_bins, keep_samples=True)
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


def summary(frame: pd.DataFrame) -> dict[str, float]:
    """The :data:`SUMMARY_KEYS` of one row's per-pair metrics."""
    agg = aggregate({k: frame[k].to_numpy() for k in frame.columns})
    return {k: agg[k] for k in SUMMARY_KEYS if k in agg}


def cross_entry(f: pd.DataFrame, au: UncertaintyAUROC) -> dict[str, float]:
    """One cell of the cross table: the :data:`CROSS_KEYS`, AUROC(u) and the success rate."""
    agg = aggregate({k: f[k].to_numpy() for k in f.columns})
    out = {k: agg[k] for k in CROSS_KEYS} | {"u_auroc": au.value()}
    if "reg_success" in f:
        out["success_rate"] = float(f["reg_success"].mean())
    return out


def tag_samples(
    frame: pd.DataFrame,
    cfg: str,
    method: str,
    d: dict[str, np.ndarray],
    idx: np.ndarray,
    network: str = "",
) -> pd.DataFrame:
    """The samples-table rows: configuration, row (method), network, pair id, the noise drawn and
    the label's mean u of each pair (``label_u_mean``)."""
    frame = frame.copy()
    nz = d["noise"][idx]
    frame.insert(0, "pair_id", np.asarray(d["pair_id"][idx], dtype=np.int64))
    frame.insert(0, "network", network)
    frame.insert(0, "method", method)
    frame.insert(0, "config", cfg)
    frame["noise_dx"], frame["noise_dy"], frame["noise_dyaw"] = nz[:, 0], nz[:, 1], nz[:, 2]
    frame["trans_err_m"] = np.hypot(nz[:, 0], nz[:, 1])
    frame["rot_err_deg"] = np.degrees(np.abs(nz[:, 2]))
    frame["label_u_mean"] = unknown_mass(np.asarray(d["label"][idx], np.float64)).mean(axis=(1, 2))
    return frame


def _bin_entry(sub: pd.DataFrame) -> dict[str, float]:
    """:data:`BIN_KEYS` of the pairs of one bin (+ ``success_rate`` of a pose-estimating row)."""
    agg = aggregate({k: sub[k].to_numpy() for k in sub.columns})
    out = {k: agg[k] for k in BIN_KEYS if k in agg}
    if "reg_success" in sub and sub["reg_success"].notna().all():
        out["success_rate"] = float(sub["reg_success"].astype(float).mean())
    return out


def pose_bins(
    frame: pd.DataFrame, trans_bins_m: Sequence[float], rot_bins_deg: Sequence[float]
) -> tuple[dict[str, Any], pd.DataFrame]:
    """Metrics per method and bin of the drawn translation / rotation error (dict and table)."""
    import pandas as pd

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
                    out[axis][meth][lab] = _bin_entry(sub)
                    rows.append({"axis": axis, "bin": lab, "method": meth, **out[axis][meth][lab]})
    return out, pd.DataFrame(rows)
