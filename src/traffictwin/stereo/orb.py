"""ORB pair check (paper 003 section 3.3, DESIGN.md "ORB pair check").

ORB features in both images, brute-force Hamming matching with cross-check, then the
paper's rule on the mean image-space offsets of the matches: a rectified pair should show
only horizontal offsets (disparities), so

    outlier  <=>  mean |dx| < ``min_dx`` (1 px)  or  mean |dy| > ``max_dy`` (5 px).

The rule is applied over *reliable* matches only (DESIGN.md explains why: with every
cross-checked match the false matches alone push mean |dy| of a perfect pair far above
5 px): matches with Hamming distance <= ``max_hamming`` bits, of those the ``best_n``
closest, summarised by the mean (paper) or the median (``statistic``). No geometric
(epipolar) filtering is done: that would hide exactly the faults the check looks for.
Pairs with fewer than ``min_reliable`` reliable matches cannot be verified and are
flagged as outliers.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import cv2
import numpy as np

from traffictwin.stereo.sgm import check_pair_shapes


@dataclass(frozen=True)
class OrbResult:
    """n_matches: cross-checked matches; n_reliable: those used; mean_dx, mean_dy: mean (or
    median) |x_L - x_R| and |y_L - y_R| over reliable matches (px, NaN if none); outlier flag."""

    n_matches: int
    n_reliable: int
    mean_dx: float
    mean_dy: float
    outlier: bool

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


def match_offsets(
    left_bgr: np.ndarray,
    right_bgr: np.ndarray,
    n_features: int = 500,
    fast_threshold: int = 12,
    n_levels: int = 4,
    edge_threshold: int = 19,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cross-checked ORB matches: (dx, dy, hamming) arrays, dx = x_L - x_R, dy = y_L - y_R (px)."""
    check_pair_shapes(left_bgr, right_bgr, "ORB check")
    gl = cv2.cvtColor(left_bgr, cv2.COLOR_BGR2GRAY) if left_bgr.ndim == 3 else left_bgr
    gr = cv2.cvtColor(right_bgr, cv2.COLOR_BGR2GRAY) if right_bgr.ndim == 3 else right_bgr
    orb = _orb(n_features, fast_threshold, n_levels, edge_threshold)
    kl, dl = orb.detectAndCompute(gl, None)
    kr, dr = orb.detectAndCompute(gr, None)
    if dl is None or dr is None or len(kl) == 0 or len(kr) == 0:
        z = np.zeros(0)
        return z, z, z
    matches = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(dl, dr)
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
        left_bgr, right_bgr, n_features, fast_threshold, n_levels, edge_threshold
    )
    keep = np.flatnonzero(ham <= max_hamming)
    keep = keep[np.argsort(ham[keep], kind="stable")][:best_n]
    n_rel = len(keep)
    if n_rel == 0:
        return OrbResult(len(dx), 0, float("nan"), float("nan"), True)
    f = np.mean if statistic == "mean" else np.median
    mdx, mdy = float(f(np.abs(dx[keep]))), float(f(np.abs(dy[keep])))
    outlier = bool(n_rel < min_reliable or mdx < min_dx or mdy > max_dy)
    return OrbResult(len(dx), n_rel, mdx, mdy, outlier)
