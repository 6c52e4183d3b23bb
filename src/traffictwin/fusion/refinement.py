"""ECC refinement of a given relative pose (e.g. the learned registration's): the classical
registration's ECC step (:func:`~traffictwin.fusion.registration.ecc_align`, coarse to fine) started
from that pose, kept only where it converges, stays within a bound of the start and improves the
masked correlation (the ``learned-refined`` fusion methods)."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from traffictwin.fusion.registration import (
    FEATURES,
    ecc_align,
    masked_cc,
    pair_features,
    pose_error,
    scored_estimate,
)
from traffictwin.grid import GridSpec

__all__ = ["RefinementParams", "RefinementResult", "refine_pose"]


@dataclass(frozen=True)
class RefinementParams:
    """Settings of :func:`refine_pose` (units in the names: m, deg, cells).

    The fallback bound (``max_trans_m``, ``max_rot_deg``) is how far the refinement may move the
    pose it starts from: set it from the starting estimate's expected error (a refinement that
    moves further has left the basin it was started in).
    """

    feature: str = "occ"  # as RegistrationParams.feature
    known_threshold: float = 0.05  # a cell is "known" where m_F + m_O > this
    ecc_iterations: int = 60
    ecc_eps: float = 1e-5
    ecc_gauss_size: int = 5  # OpenCV's blur inside ECC (odd, cells)
    ecc_levels: int = 1  # pyramid levels (1 = full resolution only; each further level halves)
    max_trans_m: float = 1.0  # largest accepted move of the translation from the start (m)
    max_rot_deg: float = 3.0  # largest accepted move of the yaw from the start (deg)
    min_gain: float = (
        0.0  # the refined masked correlation must exceed the start's by more than this
    )
    min_overlap: float = 0.05  # minimum fraction of cells known in both maps

    def __post_init__(self) -> None:
        if self.feature not in FEATURES:
            raise ValueError(
                f"RefinementParams.feature must be one of {FEATURES}, got {self.feature!r}"
            )
        if self.ecc_gauss_size < 1 or self.ecc_gauss_size % 2 == 0:
            raise ValueError(
                f"RefinementParams.ecc_gauss_size must be a positive odd integer, got {self.ecc_gauss_size}"
            )
        for name in ("ecc_iterations", "ecc_levels", "max_trans_m", "max_rot_deg"):
            if getattr(self, name) <= 0:
                raise ValueError(f"RefinementParams.{name} must be > 0, got {getattr(self, name)}")


@dataclass
class RefinementResult:
    """Outcome of :func:`refine_pose`: ``pose`` (x m, y m, yaw rad) used — the refined estimate if
    accepted, else the start; ``estimate`` the (possibly rejected) refined pose; ``ecc_ok`` ECC
    converged at full resolution; ``cc_start`` / ``cc_est`` masked correlation of the feature
    images under the start / the estimate; ``seconds`` wall time."""

    pose: np.ndarray
    accepted: bool
    ecc_ok: bool
    cc_start: float
    cc_est: float
    seconds: float
    estimate: np.ndarray


def refine_pose(
    map1: np.ndarray,
    map2: np.ndarray,
    rel_pose: np.ndarray,
    grid: GridSpec,
    params: RefinementParams = RefinementParams(),
) -> RefinementResult:
    """Refine a relative pose estimate (e.g. the learned registration's) by ECC on the maps.

    ``map1``, ``map2``: masses (2, H, W), each in its own sensor frame; ``rel_pose``: the starting
    estimate of map 2's sensor in map 1's frame (x m, y m, yaw rad). Map 2's feature image is
    warped by it, :func:`ecc_align` (the classical registration's refinement, coarse to fine over
    ``params.ecc_levels``) aligns it to map 1's from the identity. Fallback to the start when ECC
    does not converge, the refined pose moves more than ``max_trans_m`` / ``max_rot_deg`` from it,
    or its masked correlation does not beat the start's by more than ``min_gain``.
    """
    t0 = time.perf_counter()
    start = np.asarray(rel_pose, dtype=np.float64).reshape(3)
    pf = pair_features(
        "refine_pose", map1, map2, start, grid, params.feature, params.known_threshold
    )
    f1, k1, a0, g2, kg2, both = pf.f1, pf.k1, pf.a0, pf.g2, pf.kg2, pf.both
    min_cells = params.min_overlap * f1.size
    cc_start = masked_cc(f1, g2, both) if both.sum() >= min_cells else -1.0

    def result(est: np.ndarray, ok: bool, ecc_ok: bool, cc_est: float) -> RefinementResult:
        return RefinementResult(
            pose=est if ok else start.copy(),
            accepted=ok,
            ecc_ok=ecc_ok,
            cc_start=cc_start,
            cc_est=cc_est,
            seconds=time.perf_counter() - t0,
            estimate=est,
        )

    if both.sum() < min_cells:
        return result(start.copy(), False, False, cc_start)
    w, ecc_ok = ecc_align(
        f1,
        g2,
        k1,
        kg2,
        np.eye(3),
        params.ecc_iterations,
        params.ecc_eps,
        params.ecc_gauss_size,
        params.ecc_levels,
    )
    if not ecc_ok:
        return result(start.copy(), False, False, cc_start)
    a_est = np.linalg.inv(np.linalg.inv(a0) @ w)  # map2 px → map1 px
    est, cc_est = scored_estimate(pf, a_est, grid, min_cells)
    dt, dr = pose_error(est, start)
    ok = bool(
        dt <= params.max_trans_m
        and dr <= params.max_rot_deg
        and cc_est > cc_start + params.min_gain
    )
    return result(est, ok, True, cc_est)
