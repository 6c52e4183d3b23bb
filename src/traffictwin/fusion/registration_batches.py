"""Registration of a batch of pairs for the fusion methods (:mod:`traffictwin.fusion.methods`):
each pair's relative pose estimated, map 2 warped by the pose used, Dempster with map 1, per-pair
diagnostics and wall time (s) in a :class:`RegisteredBatch`.

- classical (Fourier–Mellin + ECC, :func:`~traffictwin.fusion.registration.register_pair`):
  :func:`registered_fusion` (one pair at a time, memoised per pair), :func:`register_many`
  (worker processes), :func:`precompute_registrations` (into a batch's memo),
  :func:`register_prealigned` (prealigned arrays re-warped: the ``register`` stage);
- learned (:mod:`traffictwin.fusion.learned_registration`): :func:`learned_registration_batch`;
- learned, then refined by ECC (:func:`~traffictwin.fusion.refinement.refine_pose`):
  :func:`refined_registration_batch`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from traffictwin.evidential.dempster import dempster
from traffictwin.fusion.method_input import FusionInput
from traffictwin.fusion.refinement import refine_pose
from traffictwin.fusion.registration import RegistrationParams, RegistrationResult, register_pair
from traffictwin.grid import GridSpec

__all__ = [
    "RegisteredBatch",
    "registered_fusion",
    "register_many",
    "precompute_registrations",
    "register_prealigned",
    "learned_registration_batch",
    "refined_registration_batch",
]


# -- classical registration ------------------------------------------------------------------------
@dataclass
class RegisteredBatch:
    """Output of :func:`registered_fusion`: fused masses, the poses used and per-pair diagnostics."""

    masses: np.ndarray  # (N, 2, H, W)
    warped: np.ndarray  # (N, 2, H, W) map 2 warped into map 1's frame by ``poses``
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
    params: RegistrationParams | None = None,
    memo: dict | None = None,
    keys: np.ndarray | None = None,
) -> RegisteredBatch:
    """Register each raw map 2 ``(N, 2, H, W)`` onto map 1 from the noisy pose ``(N, 3)``, warp,
    Dempster (``params``: default :class:`RegistrationParams`). ``memo`` with ``keys (N,)``: a
    pair's registration is looked up there (``("registered", key)``) or computed and stored;
    its seconds count either way."""
    from traffictwin.evidential.warp import warp_masses

    params = RegistrationParams() if params is None else params
    map1 = np.asarray(map1, dtype=np.float32)
    map2 = np.asarray(map2, dtype=np.float32)
    poses_in = np.asarray(rel_pose_noisy, dtype=np.float64).reshape(-1, 3)
    n = len(map1)
    if map2.shape != map1.shape or len(poses_in) != n:
        raise ValueError(
            f"registered_fusion: map1 {map1.shape}, map2 {map2.shape} and rel_pose_noisy {poses_in.shape} must agree on N"
        )
    out = np.empty_like(map1)
    warped = np.empty_like(map2)
    cols = {k: np.empty((n, 3)) for k in ("poses", "estimates")}
    acc = np.zeros(n, bool)
    ccn, cce, secs = np.empty(n), np.empty(n), np.empty(n)
    for i in range(n):  # per pair: OpenCV registration is inherently per image
        t0 = time.perf_counter()
        key = ("registered", int(keys[i])) if memo is not None and keys is not None else None
        if key is not None and key in memo:
            r: RegistrationResult = memo[key]
            reused = r.seconds
        else:
            r = register_pair(map1[i], map2[i], poses_in[i], grid, params)
            reused = 0.0
            if key is not None:
                memo[key] = r
        warped[i] = warp_masses(map2[i], r.pose, grid)
        out[i] = dempster(map1[i], warped[i])
        secs[i] = time.perf_counter() - t0 + reused
        cols["poses"][i], cols["estimates"][i] = r.pose, r.estimate
        acc[i], ccn[i], cce[i] = r.accepted, r.cc_noisy, r.cc_est
    return RegisteredBatch(out, warped, cols["poses"], cols["estimates"], acc, ccn, cce, secs)


_POOL_STATE: dict[str, Any] = {}  # grid and settings of :func:`register_many`'s worker processes


def _pool_init(grid: GridSpec, params: RegistrationParams) -> None:
    import cv2

    cv2.setNumThreads(1)  # one process per core: OpenCV's own threads would compete
    _POOL_STATE.update(grid=grid, params=params)


def _register_task(task: tuple[int, np.ndarray, np.ndarray, np.ndarray]) -> tuple[int, Any]:
    i, m1, m2, pose = task
    return i, register_pair(m1, m2, pose, _POOL_STATE["grid"], _POOL_STATE["params"])


def register_many(
    map1: np.ndarray,
    map2: np.ndarray,
    rel_pose_noisy: np.ndarray,
    grid: GridSpec,
    params: RegistrationParams | None = None,
    workers: int = 1,
) -> list[RegistrationResult]:
    """The classical registration (:func:`register_pair`) of every pair ``(N, 2, H, W)`` from its
    noisy pose ``(N, 3)``, in ``workers`` processes (OpenCV on one thread each: the per-image
    registration does not use two cores well). The workers come from a fork server, not a fork of
    this process (whose torch / OpenCV / logging threads could hold a lock at the fork and
    deadlock the child), and each task carries its own pair. The results are the same for any
    number of workers; each result's ``seconds`` is its own single-thread wall time."""
    from traffictwin.processes import map_indexed

    params = RegistrationParams() if params is None else params
    n = len(map1)
    poses = np.asarray(rel_pose_noisy, dtype=np.float64).reshape(-1, 3)
    if workers <= 1 or n <= 1:
        return [register_pair(map1[i], map2[i], poses[i], grid, params) for i in range(n)]
    tasks = ((i, map1[i], map2[i], poses[i]) for i in range(n))
    return map_indexed(
        _register_task,
        tasks,
        n,
        workers,
        method="forkserver",
        initializer=_pool_init,
        initargs=(grid, params),
        chunksize=4,
    )


def precompute_registrations(x: FusionInput, workers: int = 1) -> None:
    """Put the classical registration of every pair of ``x`` into ``x.memo`` (keys ``x.pair_key``)
    with :func:`register_many`, so the methods that use it (``registered``,
    ``registered+network``) find it computed once, on ``workers`` cores."""
    if x.memo is None or x.pair_key is None:
        raise ValueError("precompute_registrations: x needs memo and pair_key")
    todo = [i for i, k in enumerate(x.pair_key) if ("registered", int(k)) not in x.memo]
    if not todo:
        return
    res = register_many(
        np.asarray(x.map1, dtype=np.float32)[todo],
        np.asarray(x.map2, dtype=np.float32)[todo],
        np.asarray(x.rel_pose_noisy)[todo],
        x.grid,
        x.registration,
        workers,
    )
    for i, r in zip(todo, res):
        x.memo[("registered", int(x.pair_key[i]))] = r


def register_prealigned(
    arrays: dict[str, np.ndarray], map2: np.ndarray, grid: GridSpec, params: Any = None
) -> dict[str, np.ndarray]:
    """Prealigned ``arrays`` (:func:`traffictwin.fusion.pairs.prealign_arrays`) re-warped by classical registration.

    ``map2 (N, 2, H, W)``: the raw map 2 of each pair (its own sensor frame). Map 2 is registered
    onto map 1 (``arrays["inputs"][:, :2]``) from the noisy relative pose with
    :func:`registered_fusion` (``params``: its
    :class:`~traffictwin.fusion.registration.RegistrationParams`) and warped by the pose it uses
    (the estimate, or the noisy pose where the estimate was rejected). Returns the same keys with
    ``inputs[:, 2:]`` replaced, plus ``rel_pose_registered (N, 3)`` and ``reg_accepted (N,)``.
    """
    map1 = np.asarray(arrays["inputs"][:, :2], dtype=np.float32)
    if np.shape(map2) != map1.shape:
        raise ValueError(
            f"register_prealigned: map2 {np.shape(map2)} must match map 1 {map1.shape} (N, 2, H, W)"
        )
    b = registered_fusion(map1, map2, arrays["rel_pose_noisy"], grid, params)
    out = dict(arrays)
    out["inputs"] = np.concatenate([map1, b.warped], axis=1).astype(np.float32)
    out["rel_pose_registered"] = b.poses.astype(np.float64)
    out["reg_accepted"] = b.accepted.astype(bool)
    return out


# -- learned registration ----------------------------------------------------------------------------
def learned_registration_batch(x: FusionInput, registration: Any) -> RegisteredBatch:
    """The learned registration of a batch (prealigned inputs, noisy poses): estimate, fallback,
    map 2 warped by the pose used, Dempster; as a :class:`RegisteredBatch` (per-pair seconds =
    the batch's wall time / N). Where the raw map 2 is given (``x.map2``), it is warped once from
    its own frame by the pose used (:func:`~traffictwin.evidential.warp.warp_masses`, as
    ``registered`` does); otherwise the prealigned map 2 is re-sampled by the correction.
    With ``x.memo`` and ``x.pair_key`` the batch's result is computed once (key: the pair keys)
    and reused, its per-pair seconds unchanged."""
    import torch

    from traffictwin.evidential.warp import warp_masses
    from traffictwin.fusion.learned_registration import check_pair_inputs, correction_to_pose

    key = None
    if x.memo is not None and x.pair_key is not None:
        key = ("learned", id(registration), tuple(int(k) for k in x.pair_key))
        if key in x.memo:
            return x.memo[key]
    inputs = np.ascontiguousarray(x.inputs, dtype=np.float32)
    noisy = np.asarray(x.rel_pose_noisy, dtype=np.float64)
    check_pair_inputs(inputs, noisy, x.grid)
    t0 = time.perf_counter()
    with torch.no_grad():
        r = registration.register(torch.from_numpy(inputs), torch.from_numpy(noisy))
    m, m_used = r["m"].double().numpy(), r["m_used"].double().numpy()
    poses = correction_to_pose(m_used, noisy, x.grid)
    if x.map2 is not None:
        raw2 = np.asarray(x.map2, dtype=np.float32)
        warped = np.stack([warp_masses(raw2[i], poses[i], x.grid) for i in range(len(raw2))])
    else:
        warped = r["warped"].numpy().astype(np.float32)
    masses = dempster(inputs[:, :2], warped)
    per_pair = (time.perf_counter() - t0) / max(1, len(inputs))
    out = RegisteredBatch(
        masses=masses.astype(np.float32),
        warped=warped,
        poses=poses,
        estimates=correction_to_pose(m, noisy, x.grid),
        accepted=r["accepted"].numpy().astype(bool),
        cc_noisy=r["cc_noisy"].double().numpy(),
        cc_est=r["cc_est"].double().numpy(),
        seconds=np.full(len(inputs), per_pair),
    )
    if key is not None:
        x.memo[key] = out
    return out


# -- learned registration + ECC refinement -------------------------------------------------------------
def refined_registration_batch(x: FusionInput, registration: Any) -> RegisteredBatch:
    """The learned registration's pose (:func:`learned_registration_batch`, computed once and
    shared with ``learned``) refined per pair by :func:`~traffictwin.fusion.refinement.refine_pose`
    on the raw maps (``x.refinement``), map 2 warped from its own frame by the refined pose,
    Dempster. ``accepted``: the refinement was kept (else the learned pose is used); ``estimates``:
    the refined estimates (even where rejected); ``cc_noisy`` / ``cc_est``: masked correlation
    under the learned pose / the refined one. Per-pair seconds = learned share + own refinement."""
    from traffictwin.evidential.warp import warp_masses

    key = None
    if x.memo is not None and x.pair_key is not None:
        key = (
            "learned-refined",
            id(registration),
            x.refinement,
            tuple(int(k) for k in x.pair_key),
        )
        if key in x.memo:
            return x.memo[key]
    coarse = learned_registration_batch(x, registration)
    map1 = np.asarray(x.map1, dtype=np.float32)  # raw (its own frame): ECC's template
    fused1 = np.asarray(x.inputs[:, :2], dtype=np.float32)  # map 1 as `learned` fuses it
    map2 = np.asarray(x.map2, dtype=np.float32)
    n = len(map1)
    if map2.shape != map1.shape or len(coarse.poses) != n:
        raise ValueError(
            f"learned-refined: raw map1 {map1.shape} and map2 {map2.shape} must match the "
            f"{len(coarse.poses)} prealigned pairs"
        )
    out = np.empty_like(map1)
    warped = np.empty_like(map2)
    poses, estimates = np.empty((n, 3)), np.empty((n, 3))
    acc = np.zeros(n, bool)
    ccs, cce, secs = np.empty(n), np.empty(n), np.empty(n)
    for i in range(n):  # per pair: OpenCV's ECC is per image
        t0 = time.perf_counter()
        r = refine_pose(map1[i], map2[i], coarse.poses[i], x.grid, x.refinement)
        warped[i] = warp_masses(map2[i], r.pose, x.grid)
        out[i] = dempster(fused1[i], warped[i])
        secs[i] = time.perf_counter() - t0 + coarse.seconds[i]
        poses[i], estimates[i] = r.pose, r.estimate
        acc[i], ccs[i], cce[i] = r.accepted, r.cc_start, r.cc_est
    b = RegisteredBatch(out, warped, poses, estimates, acc, ccs, cce, secs)
    if key is not None:
        x.memo[key] = b
    return b
