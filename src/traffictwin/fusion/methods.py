"""Rule-based fusion baselines evaluated against the network (issue #5).

Every method maps one configuration's prealigned test data to fused masses ``(N, 2, H, W)`` in
map 1's frame, so all methods see the same noise draws:

- ``ego``: map 1 alone (what a vehicle knows without cooperation);
- ``naive``: map 2 warped by the *noisy* relative pose (the prealigned input channels 2–3), then
  Dempster's rule — the paper's baseline;
- ``naive-yager`` / ``naive-cautious``: the same warped maps combined with Yager's rule
  (conflict → unknown) or Denœux's normalised cautious rule (:mod:`traffictwin.evidential.rules`);
- ``registered``: classical registration of the raw map 2 onto map 1 starting from the noisy pose
  (:mod:`traffictwin.fusion.registration`), map 2 warped by the estimate with the project's
  warp (``traffictwin.evidential.warp.warp_masses``), then Dempster.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from traffictwin.fusion.registration import RegistrationParams, RegistrationResult, register_pair
from traffictwin.grid import GridSpec

if TYPE_CHECKING:
    import pandas as pd

    from traffictwin.fusion.metrics import UncertaintyAUROC

__all__ = [
    "PREALIGNED_METHODS",
    "METHODS",
    "fuse_prealigned",
    "registered_fusion",
    "RegisteredBatch",
    "EvalSettings",
    "evaluate_predictions",
    "evaluate_prealigned",
    "evaluate_registered",
]

PREALIGNED_METHODS = ("ego", "naive", "naive-yager", "naive-cautious")
METHODS = (*PREALIGNED_METHODS, "registered")


def _rule(method: str) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    if method == "naive":
        from traffictwin.evidential.dempster import dempster

        return dempster
    if method == "naive-yager":
        from traffictwin.evidential.rules import yager

        return yager
    if method == "naive-cautious":
        from traffictwin.evidential.rules import cautious

        return cautious
    raise ValueError(
        f"unknown prealigned fusion method {method!r} (expected one of {PREALIGNED_METHODS})"
    )


def fuse_prealigned(inputs: np.ndarray, method: str) -> np.ndarray:
    """Fuse prealigned inputs ``(N, 4, H, W)`` = [m_F1, m_O1, m_F2', m_O2'] with ``method`` → ``(N, 2, H, W)`` float32."""
    inputs = np.asarray(inputs)
    if inputs.ndim != 4 or inputs.shape[1] != 4:
        raise ValueError(
            f"fuse_prealigned: inputs must have shape (N, 4, H, W), got {inputs.shape}"
        )
    m1 = inputs[:, 0:2]
    if method == "ego":
        return np.ascontiguousarray(m1, dtype=np.float32)
    return np.asarray(_rule(method)(m1, inputs[:, 2:4]), dtype=np.float32)


@dataclass
class RegisteredBatch:
    """Output of :func:`registered_fusion`: fused masses, the poses used and per-pair diagnostics."""

    masses: np.ndarray  # (N, 2, H, W)
    poses: np.ndarray  # (N, 3) relative pose used (estimate or noisy fallback)
    estimates: np.ndarray  # (N, 3) registration estimate (even when rejected)
    accepted: np.ndarray  # (N,) bool
    cc_noisy: np.ndarray  # (N,)
    cc_est: np.ndarray  # (N,)
    seconds: np.ndarray  # (N,) wall time per pair incl. warp + Dempster (s)


def registered_fusion(
    map1: np.ndarray,
    map2: np.ndarray,
    rel_pose_noisy: np.ndarray,
    grid: GridSpec,
    params: RegistrationParams = RegistrationParams(),
) -> RegisteredBatch:
    """Register each raw map 2 ``(N, 2, H, W)`` onto map 1 from the noisy pose ``(N, 3)``, warp, Dempster."""
    from traffictwin.evidential.dempster import dempster
    from traffictwin.evidential.warp import warp_masses

    map1 = np.asarray(map1, dtype=np.float32)
    map2 = np.asarray(map2, dtype=np.float32)
    poses_in = np.asarray(rel_pose_noisy, dtype=np.float64).reshape(-1, 3)
    n = len(map1)
    if map2.shape != map1.shape or len(poses_in) != n:
        raise ValueError(
            f"registered_fusion: map1 {map1.shape}, map2 {map2.shape} and rel_pose_noisy {poses_in.shape} must agree on N"
        )
    out = np.empty_like(map1)
    poses = np.empty((n, 3))
    est = np.empty((n, 3))
    acc = np.zeros(n, bool)
    ccn = np.empty(n)
    cce = np.empty(n)
    secs = np.empty(n)
    for i in range(n):  # per pair: OpenCV registration is inherently per image
        t0 = time.perf_counter()
        r: RegistrationResult = register_pair(map1[i], map2[i], poses_in[i], grid, params)
        warped = warp_masses(map2[i], r.pose, grid)
        out[i] = dempster(map1[i], warped)
        secs[i] = time.perf_counter() - t0
        poses[i], est[i], acc[i], ccn[i], cce[i] = (
            r.pose,
            r.estimate,
            r.accepted,
            r.cc_noisy,
            r.cc_est,
        )
    return RegisteredBatch(out, poses, est, acc, ccn, cce, secs)


# -- evaluation runner ---------------------------------------------------------------------------
@dataclass(frozen=True)
class EvalSettings:
    """How per-sample metrics are computed (units in the names)."""

    batch_size: int = 8
    kld_eps: float = 1e-7
    auroc_bins: int = 4096
    success_trans_m: float = 0.5
    success_rot_deg: float = 1.0


def _batches(n: int, size: int):
    for s in range(0, n, max(1, size)):
        yield slice(s, min(n, s + size))


def _rows(metrics: dict[str, np.ndarray], **cols) -> pd.DataFrame:
    import pandas as pd

    frame = pd.DataFrame(metrics)
    for k, v in cols.items():
        frame[k] = v
    return frame


def evaluate_predictions(
    label: np.ndarray,
    predict: Callable[[slice], np.ndarray],
    settings: EvalSettings,
    n: int | None = None,
) -> tuple[pd.DataFrame, UncertaintyAUROC]:
    """Metrics of ``predict(batch_slice) → (B, 2, H, W)`` masses against ``label[batch_slice]``.

    Returns per-sample metrics (one row per sample, plus ``ms`` = the prediction's wall time per
    pair in ms for its batch) and the streaming u-AUROC of the whole set.
    """
    import pandas as pd

    from traffictwin.fusion.metrics import UncertaintyAUROC, per_sample_metrics

    n = len(label) if n is None else n
    auroc = UncertaintyAUROC(bins=settings.auroc_bins)
    parts = []
    for sl in _batches(n, settings.batch_size):
        t0 = time.perf_counter()
        pred = np.asarray(predict(sl))
        ms = 1000.0 * (time.perf_counter() - t0) / (sl.stop - sl.start)
        if pred.shape != label[sl].shape:
            raise ValueError(
                f"prediction shape {pred.shape} != label shape {label[sl].shape} for samples {sl.start}:{sl.stop}"
            )
        auroc.update(label[sl], pred)
        parts.append(_rows(per_sample_metrics(label[sl], pred, settings.kld_eps), ms=ms))
    return pd.concat(parts, ignore_index=True), auroc


def evaluate_prealigned(
    inputs: np.ndarray, label: np.ndarray, method: str, settings: EvalSettings
) -> tuple[pd.DataFrame, UncertaintyAUROC]:
    """Per-sample metrics of a prealigned baseline (``ego`` / ``naive`` / ``naive-yager`` / ``naive-cautious``)."""
    if method not in PREALIGNED_METHODS:
        raise ValueError(
            f"unknown prealigned fusion method {method!r} (expected one of {PREALIGNED_METHODS})"
        )
    return evaluate_predictions(label, lambda sl: fuse_prealigned(inputs[sl], method), settings)


def evaluate_registered(
    map1: np.ndarray,
    map2: np.ndarray,
    rel_pose_noisy: np.ndarray,
    rel_pose_true: np.ndarray,
    label: np.ndarray,
    grid: GridSpec,
    params: RegistrationParams,
    settings: EvalSettings,
) -> tuple[pd.DataFrame, UncertaintyAUROC]:
    """Per-sample metrics of ``registered`` plus residual pose errors and success flags.

    Extra columns: ``reg_accepted``, ``reg_trans_err_m`` / ``reg_rot_err_deg`` (residual error of the
    pose used), ``est_trans_err_m`` / ``est_rot_err_deg`` (of the raw estimate), ``noisy_trans_err_m``
    / ``noisy_rot_err_deg`` (of the noisy pose), ``reg_success`` (residual within
    ``success_trans_m`` and ``success_rot_deg``), ``reg_cc_noisy`` / ``reg_cc_est``.
    """
    from traffictwin.fusion.registration import pose_error

    store: dict[str, RegisteredBatch] = {}

    def predict(sl: slice) -> np.ndarray:
        b = registered_fusion(map1[sl], map2[sl], rel_pose_noisy[sl], grid, params)
        store[f"{sl.start}"] = b
        return b.masses

    frame, auroc = evaluate_predictions(label, predict, settings)
    b = [store[k] for k in sorted(store, key=int)]
    poses = np.concatenate([x.poses for x in b])
    est = np.concatenate([x.estimates for x in b])
    true = np.asarray(rel_pose_true, dtype=np.float64)[: len(poses)]
    t, r = pose_error(poses, true)
    te, re = pose_error(est, true)
    tn, rn = pose_error(np.asarray(rel_pose_noisy, dtype=np.float64)[: len(poses)], true)
    frame["reg_accepted"] = np.concatenate([x.accepted for x in b])
    frame["reg_trans_err_m"], frame["reg_rot_err_deg"] = t, r
    frame["est_trans_err_m"], frame["est_rot_err_deg"] = te, re
    frame["noisy_trans_err_m"], frame["noisy_rot_err_deg"] = tn, rn
    frame["reg_success"] = (t <= settings.success_trans_m) & (r <= settings.success_rot_deg)
    frame["reg_cc_noisy"] = np.concatenate([x.cc_noisy for x in b])
    frame["reg_cc_est"] = np.concatenate([x.cc_est for x in b])
    frame["ms"] = 1000.0 * np.concatenate([x.seconds for x in b])
    return frame, auroc
