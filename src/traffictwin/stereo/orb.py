"""ORB pair check (paper 003 section 3.3, docs/design.md "ORB pair check").

ORB features in both images, brute-force Hamming matching with cross-check, then the
paper's rule on the mean image-space offsets of the matches: a rectified pair should show
only horizontal offsets (disparities), so

    outlier  <=>  mean |dx| < ``min_dx`` (1 px)  or  mean |dy| > ``max_dy`` (5 px)
                  (or the cameras are swapped: median signed dx <= -``min_dx``, below).

The rule is applied over *reliable* matches only (docs/design.md explains why: with every
cross-checked match the false matches alone push mean |dy| of a perfect pair far above
5 px): matches with Hamming distance <= ``max_hamming`` bits, of those the ``best_n``
closest, summarised by the mean (paper) or the median (``statistic``). No geometric
(epipolar) filtering is done: that would hide exactly the faults the check looks for.
Pairs with fewer than ``min_reliable`` reliable matches cannot be verified and are
flagged as outliers (uniform or textureless images yield none). The rule on |dx| cannot tell a
pair whose cameras are swapped from a good one, so the sign is checked too: in a rectified
left/right pair a point's x in the left image is >= its x in the right one, so the median signed
dx = x_L - x_R of the reliable matches is >= 0; a median at or below ``-min_dx`` (px: a disparity
of at least ``min_dx`` in the wrong direction) flags the pair as ``swapped``. The means over
*all* cross-checked matches are kept too (``all_mean_dx``,
``all_mean_dy``): the paper's literal rule, compared in :mod:`traffictwin.stereo.check`.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from traffictwin.config import spec
from traffictwin.stereo.sgm import check_pair_shapes

if TYPE_CHECKING:  # pandas only in annotations: importing this module for one pair stays light
    import pandas as pd

#: the ``fault`` value of a fault-free pair
NO_FAULT = "none"
#: orb.csv columns, in order: the robust rule's statistics, ``outlier`` (drop the pair: the
#: configured rule of :mod:`traffictwin.stereo.check`), the paper's all-match means, the SGM valid
#: share, one flag per rule and the injected fault
TABLE_COLUMNS = (
    "frame_id",
    "n_matches",
    "n_reliable",
    "mean_dx",
    "mean_dy",
    "outlier",
    "all_mean_dx",
    "all_mean_dy",
    "valid_share",
    "flag_orb_paper",
    "flag_orb",
    "flag_valid_share",
    "fault",
)
#: |dy| thresholds (px) of the sensitivity sweep in orb.json
SWEEP_MAX_DY = (1.0, 2.0, 3.0, 5.0)


@dataclass
class OrbParams:
    """``risk_data.orb``: detector (features, FAST threshold, pyramid levels, edge = patch size px)
    and the rule (reliable = Hamming <= ``max_hamming`` bits, the ``best_n`` best; fewer than
    ``min_reliable`` -> flagged; ``statistic`` of |dx|, |dy|; ``min_dx``/``max_dy`` px)."""

    n_features: int = spec(min=10)
    fast_threshold: int = spec(min=1)
    n_levels: int = spec(min=1)
    edge_threshold: int = spec(min=3)
    max_hamming: float = spec(min=0)
    best_n: int = spec(min=1)
    min_reliable: int = spec(min=1)
    statistic: str = spec(choices=("mean", "median"))
    min_dx: float = spec(min=0)
    max_dy: float = spec(min=0)

    def detector(self) -> dict[str, int]:
        """The detector's keyword arguments (for :func:`match_offsets` and the figure)."""
        return {
            "n_features": self.n_features,
            "fast_threshold": self.fast_threshold,
            "n_levels": self.n_levels,
            "edge_threshold": self.edge_threshold,
        }


@dataclass(frozen=True)
class OrbResult:
    """n_matches: cross-checked matches; n_reliable: those used; mean_dx, mean_dy: mean (or
    median) |x_L - x_R| and |y_L - y_R| over reliable matches (px, NaN if none); outlier flag
    (the robust rule, swapped cameras included); all_mean_dx, all_mean_dy: means over all
    cross-checked matches (px, NaN if none: the paper's literal statistics); median_dx: median
    signed x_L - x_R over reliable matches (px, NaN if none); swapped: that median is at or
    below ``-min_dx``; reason: why the pair is an outlier, in one phrase ("" when it is not)."""

    n_matches: int
    n_reliable: int
    mean_dx: float
    mean_dy: float
    outlier: bool
    all_mean_dx: float = float("nan")
    all_mean_dy: float = float("nan")
    median_dx: float = float("nan")
    swapped: bool = False
    reason: str = ""

    def as_dict(self) -> dict:
        return asdict(self)


_ORB_CACHE: dict[tuple, cv2.ORB] = {}


def _orb(n_features: int, fast_threshold: int, n_levels: int, edge_threshold: int) -> cv2.ORB:
    key = (n_features, fast_threshold, n_levels, edge_threshold)
    if key not in _ORB_CACHE:
        _ORB_CACHE[key] = cv2.ORB.create(
            nfeatures=n_features,
            scaleFactor=1.2,
            nlevels=n_levels,
            edgeThreshold=edge_threshold,
            patchSize=edge_threshold,
            fastThreshold=fast_threshold,
        )
    return _ORB_CACHE[key]


def cross_checked_matches(
    left_bgr: np.ndarray,
    right_bgr: np.ndarray,
    n_features: int = 500,
    fast_threshold: int = 12,
    n_levels: int = 4,
    edge_threshold: int = 19,
) -> tuple[Sequence[cv2.KeyPoint], Sequence[cv2.KeyPoint], list[cv2.DMatch]]:
    """ORB keypoints of both images and their brute-force Hamming matches with cross-check
    (``queryIdx`` indexes the left keypoints, ``trainIdx`` the right ones; no matches if either
    image has no features)."""
    check_pair_shapes(left_bgr, right_bgr, "ORB check")
    gl = cv2.cvtColor(left_bgr, cv2.COLOR_BGR2GRAY) if left_bgr.ndim == 3 else left_bgr
    gr = cv2.cvtColor(right_bgr, cv2.COLOR_BGR2GRAY) if right_bgr.ndim == 3 else right_bgr
    orb = _orb(n_features, fast_threshold, n_levels, edge_threshold)
    kl, dl = orb.detectAndCompute(gl, None)
    kr, dr = orb.detectAndCompute(gr, None)
    if dl is None or dr is None or len(kl) == 0 or len(kr) == 0:
        return kl, kr, []
    return kl, kr, list(cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(dl, dr))


def match_offsets(
    kl: Sequence[cv2.KeyPoint], kr: Sequence[cv2.KeyPoint], matches: Sequence[cv2.DMatch]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(dx, dy, hamming) arrays of :func:`cross_checked_matches`' output, dx = x_L - x_R,
    dy = y_L - y_R (px)."""
    if not matches:
        z = np.zeros(0)
        return z, z, z
    qi = np.array([m.queryIdx for m in matches])
    ti = np.array([m.trainIdx for m in matches])
    ham = np.array([m.distance for m in matches], float)
    pl = np.array([k.pt for k in kl])[qi]
    pr = np.array([k.pt for k in kr])[ti]
    return pl[:, 0] - pr[:, 0], pl[:, 1] - pr[:, 1], ham


def check_pair(
    left_bgr: np.ndarray,
    right_bgr: np.ndarray,
    min_dx: float = 1.0,
    max_dy: float = 5.0,
    max_hamming: float = 40.0,
    best_n: int = 50,
    min_reliable: int = 8,
    statistic: str = "mean",
    n_features: int = 500,
    fast_threshold: int = 12,
    n_levels: int = 4,
    edge_threshold: int = 19,
) -> OrbResult:
    """Run the ORB pair check on a rectified BGR pair (see module docstring; thresholds in px/bits)."""
    if statistic not in ("mean", "median"):
        raise ValueError(f"orb statistic must be 'mean' or 'median', got {statistic!r}")
    if best_n < 1 or min_reliable < 1:
        raise ValueError(f"orb best_n and min_reliable must be >= 1, got {best_n}, {min_reliable}")
    dx, dy, ham = match_offsets(
        *cross_checked_matches(
            left_bgr, right_bgr, n_features, fast_threshold, n_levels, edge_threshold
        )
    )
    nan = float("nan")
    adx, ady = (float(np.abs(dx).mean()), float(np.abs(dy).mean())) if len(dx) else (nan, nan)
    keep = np.flatnonzero(ham <= max_hamming)
    keep = keep[np.argsort(ham[keep], kind="stable")][:best_n]
    n_rel = len(keep)
    if n_rel == 0:
        why = f"no reliable ORB match ({len(dx)} cross-checked): uniform or textureless images"
        return OrbResult(len(dx), 0, nan, nan, True, adx, ady, reason=why)
    f = np.mean if statistic == "mean" else np.median
    mdx, mdy = float(f(np.abs(dx[keep]))), float(f(np.abs(dy[keep])))
    sdx = float(np.median(dx[keep]))
    swapped = bool(n_rel >= min_reliable and sdx < 0 and sdx <= -min_dx)
    reasons = (
        (
            n_rel < min_reliable,
            f"{n_rel} reliable ORB matches < {min_reliable}: too little texture",
        ),
        (mdx < min_dx, f"{statistic} |dx| {mdx:.2f} px < {min_dx:g} px: no disparity"),
        (mdy > max_dy, f"{statistic} |dy| {mdy:.2f} px > {max_dy:g} px: not rectified"),
        (swapped, f"median dx {sdx:.2f} px <= -{min_dx:g} px: left and right images swapped"),
    )
    why = "; ".join(text for hit, text in reasons if hit)
    return OrbResult(len(dx), n_rel, mdx, mdy, bool(why), adx, ady, sdx, swapped, why)


def check_pairs(left: np.ndarray, right: np.ndarray, params: OrbParams) -> tuple[list[dict], float]:
    """:func:`check_pair` on every pair of the stacks ``left``/``right``: one
    :meth:`OrbResult.as_dict` per pair (with ``idx``) and the seconds spent (timing only)."""
    rows, secs = [], 0.0
    kw = asdict(params)
    for k in range(len(left)):
        t0 = time.perf_counter()
        r = check_pair(left[k], right[k], **kw)
        secs += time.perf_counter() - t0
        rows.append({"idx": k, **r.as_dict()})
    return rows, secs


def orb_frames(frames: pd.DataFrame, results: pd.DataFrame) -> pd.DataFrame:
    """Per-pair results (``shard``, ``idx``, :class:`OrbResult` fields) joined with the frames
    table (``frame_id``, ``shard``, ``idx``, ``scenario``, ``split``, ``fault``, ``speed``), by
    frame id."""
    df = frames[["frame_id", "shard", "idx", "scenario", "split", "fault", "speed"]].merge(
        results, on=["shard", "idx"], validate="one_to_one"
    )
    return df.sort_values("frame_id").reset_index(drop=True)


def orb_metrics(
    df: pd.DataFrame,
    splits: Sequence[str],
    faults: Sequence[str],
    min_reliable: int,
    min_dx: float,
) -> dict:
    """Detection rate (``outlier`` among faulty pairs, per fault type), false-alarm rate (among
    fault-free pairs), dropped share; also split by speed (faults are invisible at standstill).
    ``df``: :func:`orb_frames`; ``splits``/``faults``: the values of its ``split``/``fault``
    columns to report on (``"none"`` = fault-free is never a fault group).

    ``sweep/*``: sensitivity of the robust ORB rule's |dy| threshold on the same per-pair
    statistics (no re-matching), with the configured ``min_reliable`` (matches) and ``min_dx`` (px)
    and the swap rule (``swapped``, where ``df`` has it).
    """
    m: dict = {"all/frames": int(len(df)), "all/dropped_share": float(df.outlier.mean())}
    faulty = df.fault != NO_FAULT
    faults = [f for f in faults if f != NO_FAULT]

    def share(flag: pd.Series, sel: pd.Series) -> float:
        return float(flag[sel].mean()) if sel.any() else float("nan")

    m["all/false_alarm_rate"] = share(df.outlier, ~faulty)
    if faulty.any():
        m["all/detection_rate"] = float(df.outlier[faulty].mean())
    for f in faults:
        sel = df.fault == f
        m[f"all/faults_{f}"] = int(sel.sum())
        if sel.any():
            m[f"{f}/detection_rate"] = float(df.outlier[sel].mean())
            mov = sel & (df.speed >= 5.0)
            if mov.any():
                m[f"{f}/detection_rate_speed_ge_5"] = float(df.outlier[mov].mean())
    for s in splits:
        part = df[df.split == s]
        if len(part):
            m[f"{s}/dropped_share"] = float(part.outlier.mean())
    for thr in SWEEP_MAX_DY:
        flag = (
            (df.n_reliable < min_reliable)
            | (df.mean_dx < min_dx)
            | (df.mean_dy > thr)
            | df.mean_dy.isna()
            | (df["swapped"].astype(bool) if "swapped" in df else False)  # the swap rule
        )
        m[f"sweep/max_dy_{thr:g}_false_alarm_rate"] = share(flag, ~faulty)
        for f in faults:
            sel = df.fault == f
            if sel.any():
                m[f"sweep/max_dy_{thr:g}_{f}_detection_rate"] = float(flag[sel].mean())
    m["none/mean_dy_median"] = (
        float(df.mean_dy[~faulty].median()) if (~faulty).any() else float("nan")
    )
    m["none/mean_dx_median"] = (
        float(df.mean_dx[~faulty].median()) if (~faulty).any() else float("nan")
    )
    return m
