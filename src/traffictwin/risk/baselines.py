"""Baselines for the risk network, evaluated on the same test frames.

* :func:`constant_predictions` — the training-set mean (the MSE-optimal constant) and the
  training-set median. The median is also the *majority-class* predictor at every THW
  threshold at once: the median is above a threshold exactly when more than half of the
  training frames are critical at it.
* :func:`fit_speed_only` — the risk as a monotone (non-decreasing) function of the subject speed
  alone, fitted on the training split by isotonic regression (:class:`SpeedOnly`). It is the
  fair floor for a network that is given the speed: whatever a network gains over it comes from
  the image / disparity. (Every vehicle knows its speed; a label that is nearly a function of
  speed is solved by this baseline.)
* :func:`geometric_risk` — a non-learned stereo baseline: back-project the SGM disparity with the
  camera intrinsics, keep the points inside the subject's corridor (lateral ``|y| <=
  corridor_half_width`` in the vehicle frame, height above ground in ``[min_height, max_height]``
  — so neither the road surface nor overhanging structures count), take the robust nearest one
  (the ``min_pixels``-th smallest free distance, which rejects isolated SGM mismatches), measure
  its free distance from the subject's front bumper segment as the risk metric does
  (:mod:`traffictwin.risk.metric`), and turn it into THW with the *true* subject speed.
  It cannot tell vehicles from walls or poles, and sees only what the camera sees.

Geometry (docs/design.md, :mod:`traffictwin.sim.camera`): camera frame X right, Y down, Z forward
(m); the left optical centre is ``mount_x`` ahead of the vehicle reference point (footprint
centre), ``baseline / 2`` to its left, ``mount_height`` above the ground. A pixel (u, v) with
disparity d > 0 lies at Z = fx·B/d, X = (u − cx)·Z/fx, Y = (v − cy)·Z/fy; vehicle frame
x = mount_x + Z, y = B/2 − X, z = mount_height − Y.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from traffictwin.risk.metric import thw_to_risk


@dataclass(frozen=True)
class SpeedOnly:
    """A fitted speed-only predictor: piecewise-linear through ``(speed_knots, risk_knots)``
    (m/s → normalised risk), constant beyond the first / last knot."""

    speed_knots: np.ndarray
    risk_knots: np.ndarray

    def predict(self, speed: np.ndarray) -> np.ndarray:
        """Normalised risk (N,) float64 for subject speeds ``speed`` (N,) in m/s."""
        speed = np.asarray(speed, np.float64)
        if not np.all(np.isfinite(speed)):
            raise ValueError("speed-only baseline: speeds must be finite (m/s)")
        return np.interp(speed, self.speed_knots, self.risk_knots)

    def critical_speed(self, threshold: float) -> float:
        """The lowest speed (m/s) at which the prediction exceeds the risk ``threshold``
        (``inf`` when it never does): above it the baseline calls every frame critical."""
        above = np.flatnonzero(self.risk_knots > threshold)
        if not above.size:
            return float("inf")
        i = int(above[0])
        if i == 0:
            return float(self.speed_knots[0])
        s0, s1 = self.speed_knots[i - 1], self.speed_knots[i]
        r0, r1 = self.risk_knots[i - 1], self.risk_knots[i]
        return float(s0 + (threshold - r0) * (s1 - s0) / (r1 - r0))  # where the segment crosses it


def fit_speed_only(train_speed: np.ndarray, train_y: np.ndarray) -> SpeedOnly:
    """Isotonic (non-decreasing) regression of the normalised risk ``train_y`` on the subject
    speed ``train_speed`` (m/s) over the training frames (pool-adjacent-violators, least squares).

    Risk rises with speed at a fixed gap (THW = gap / speed), so the fit is constrained to be
    monotone; it predicts the mean training risk of the speeds around each test speed.
    """
    from sklearn.isotonic import IsotonicRegression

    x = np.asarray(train_speed, np.float64).ravel()
    y = np.asarray(train_y, np.float64).ravel()
    if x.shape != y.shape:
        raise ValueError(f"speed-only baseline: {x.size} speeds but {y.size} labels")
    if x.size == 0:
        raise ValueError("speed-only baseline needs training frames (the training split is empty)")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise ValueError("speed-only baseline: training speeds and labels must be finite")
    iso = IsotonicRegression(increasing=True, out_of_bounds="clip").fit(x, y)
    return SpeedOnly(
        np.asarray(iso.X_thresholds_, np.float64), np.asarray(iso.y_thresholds_, np.float64)
    )


def constant_predictions(train_y: np.ndarray, n: int) -> dict[str, np.ndarray]:
    """``train_mean`` and ``train_median`` (= majority class) constant predictions for ``n`` frames."""
    train_y = np.asarray(train_y, np.float64)
    if len(train_y) == 0:
        raise ValueError("constant baselines need training labels (the training split is empty)")
    return {
        "train_mean": np.full(n, float(np.mean(train_y)), np.float32),
        "train_median": np.full(n, float(np.median(train_y)), np.float32),
    }


@dataclass(frozen=True)
class GeometricParams:
    """Corridor and robustness settings of :func:`geometric_risk` (m, px counts).

    ``subject_length``/``subject_width`` must match the risk metric's subject footprint (risk data).
    """

    corridor_half_width: float = 2.0
    min_height: float = 0.3
    max_height: float = 2.5
    min_pixels: int = 10
    max_range: float = 80.0
    subject_length: float = 4.5
    subject_width: float = 1.8

    def __post_init__(self) -> None:
        if self.corridor_half_width <= 0 or self.max_range <= 0:
            raise ValueError("geometric baseline: corridor_half_width and max_range must be > 0 m")
        if not self.min_height < self.max_height:
            raise ValueError("geometric baseline: min_height must be < max_height (m)")
        if self.min_pixels < 1:
            raise ValueError("geometric baseline: min_pixels must be >= 1")
        if self.subject_length <= 0 or self.subject_width <= 0:
            raise ValueError("geometric baseline: subject_length/subject_width must be > 0 m")


_CAMERA_KEYS = ("fx", "fy", "cx", "cy", "baseline", "mount_x", "mount_height")


def _corridor_points(
    disp: np.ndarray, camera: Mapping[str, float], params: GeometricParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel of ``disp`` (N, H, W): whether it is an obstacle point ahead (valid, within
    ``max_range``, height in ``[min_height, max_height]``, ahead of the front bumper), its lateral
    offset ``y`` (m, vehicle frame, left positive) and its free distance (m) from the subject's
    front bumper segment (as the risk metric measures it)."""
    missing = [k for k in _CAMERA_KEYS if k not in camera]
    if missing:
        raise ValueError(f"camera intrinsics: key(s) {missing} missing (have {sorted(camera)})")
    disp = np.asarray(disp, np.float32)
    if disp.ndim != 3:
        raise ValueError(f"disparity: expected (N, H, W), got shape {disp.shape}")
    n, h, w = disp.shape
    if (
        "width" in camera
        and "height" in camera
        and (int(camera["width"]), int(camera["height"])) != (w, h)
    ):
        raise ValueError(
            f"disparity is {w}×{h} px but the camera intrinsics are for {int(camera['width'])}×{int(camera['height'])}"
        )
    fx, fy, cx, cy = (float(camera[k]) for k in ("fx", "fy", "cx", "cy"))
    B, mx, mh = float(camera["baseline"]), float(camera["mount_x"]), float(camera["mount_height"])
    valid = np.isfinite(disp) & (disp > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        Z = np.where(valid, (fx * B) / np.where(valid, disp, 1.0), np.inf)
    u = (np.arange(w, dtype=np.float32) - cx)[None, None, :]
    v = (np.arange(h, dtype=np.float32) - cy)[None, :, None]
    X = u * Z / fx
    Y = v * Z / fy
    x = mx + Z
    y = B / 2.0 - X
    z = mh - Y
    keep = (
        valid
        & (Z <= params.max_range)
        & (z >= params.min_height)
        & (z <= params.max_height)
        & (x > params.subject_length / 2.0)
    )
    dx = x - params.subject_length / 2.0
    dy = np.maximum(np.abs(y) - params.subject_width / 2.0, 0.0)
    with np.errstate(invalid="ignore"):
        dist = np.where(keep, np.hypot(dx, dy), np.inf)
    return keep, np.where(keep, y, np.nan), dist


def _robust_min(dist: np.ndarray, min_pixels: int) -> np.ndarray:
    """The ``min_pixels``-th smallest value of each frame of ``dist`` (N, ...) (inf: fewer)."""
    d = dist.reshape(dist.shape[0], -1)
    k = min(min_pixels, d.shape[1]) - 1
    return np.partition(d, k, axis=1)[:, k].astype(np.float64)


def _in_chunks(fn, disp: np.ndarray, chunk: int) -> np.ndarray:
    """``fn`` over ``chunk`` frames of ``disp`` (N, H, W) at a time (memory), rows concatenated."""
    disp = np.asarray(disp, np.float32)
    if disp.ndim != 3 or disp.shape[0] <= chunk:
        return fn(disp)
    return np.concatenate([fn(disp[i : i + chunk]) for i in range(0, disp.shape[0], chunk)])


def corridor_distances(
    disp: np.ndarray,
    camera: Mapping[str, float],
    params: GeometricParams,
    half_widths: Sequence[float],
    chunk: int = 32,
) -> np.ndarray:
    """Free distance (m) to the robust nearest obstacle in straight corridors of several
    half-widths (m) at once: (N, K) float64 for ``half_widths`` (K,), ``inf`` where fewer than
    ``min_pixels`` points lie in a corridor. ``params.corridor_half_width`` is not used.
    One back-projection per frame serves every width (the validation tuning scores all)."""
    hw = np.asarray(list(half_widths), np.float64)
    if hw.ndim != 1 or hw.size == 0 or not np.all(hw > 0):
        raise ValueError(f"corridor half-widths must be a non-empty list of metres > 0, got {hw}")

    def one(d: np.ndarray) -> np.ndarray:
        _, y, dist = _corridor_points(d, camera, params)
        ay = np.abs(y)
        return np.stack(
            [_robust_min(np.where(ay <= w, dist, np.inf), params.min_pixels) for w in hw], axis=1
        )

    return _in_chunks(one, disp, chunk)


def lateral_bin_distances(
    disp: np.ndarray,
    camera: Mapping[str, float],
    params: GeometricParams,
    edges: Sequence[float],
    chunk: int = 32,
) -> np.ndarray:
    """Free distance (m) to the robust nearest obstacle in each lateral strip ``[edges[i],
    edges[i+1])`` (m, vehicle frame, left positive): (N, len(edges) - 1) float64, ``inf`` where
    a strip holds fewer than ``min_pixels`` points — a bird's-eye profile of what is ahead."""
    e = np.asarray(list(edges), np.float64)
    if e.ndim != 1 or e.size < 2 or not np.all(np.diff(e) > 0):
        raise ValueError(f"lateral bin edges must be >= 2 increasing metres, got {e}")

    def one(d: np.ndarray) -> np.ndarray:
        _, y, dist = _corridor_points(d, camera, params)
        b = np.digitize(np.nan_to_num(y, nan=np.inf), e) - 1  # -1 / len(e)-1: outside every strip
        return np.stack(
            [
                _robust_min(np.where(b == i, dist, np.inf), params.min_pixels)
                for i in range(e.size - 1)
            ],
            axis=1,
        )

    return _in_chunks(one, disp, chunk)


def geometric_distance(
    disp: np.ndarray, camera: Mapping[str, float], params: GeometricParams, chunk: int = 32
) -> np.ndarray:
    """Free distance (m) from the front bumper to the robust nearest obstacle in the corridor, per frame.

    ``disp``: (N, H, W) disparity in px at the camera's resolution (≤ 0 or non-finite = invalid).
    Returns (N,) float64, ``inf`` where fewer than ``min_pixels`` valid points lie in the corridor
    ``|y| <= corridor_half_width``. Processed ``chunk`` frames at a time (memory).
    """
    return corridor_distances(disp, camera, params, [params.corridor_half_width], chunk)[:, 0]


def thw_from_distance(dist: np.ndarray, speed: np.ndarray) -> np.ndarray:
    """THW (s) = free distance (m) / speed (m/s); speed 0 or nothing ahead → inf."""
    dist = np.asarray(dist, np.float64)
    speed = np.asarray(speed, np.float64)
    if speed.shape != dist.shape[: speed.ndim]:
        raise ValueError(f"speed has shape {speed.shape}, expected ({len(dist)},)")
    sp = speed.reshape(speed.shape + (1,) * (dist.ndim - speed.ndim))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(sp > 0, dist / np.where(sp > 0, sp, 1.0), np.inf)


def geometric_risk(
    disp: np.ndarray, speed: np.ndarray, camera: Mapping[str, float], params: GeometricParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(distance m, THW s, normalised risk) per frame from SGM disparity and the true speed (m/s).

    THW = distance / speed; speed 0 or nothing in the corridor → THW inf, risk 0.
    """
    dist = geometric_distance(disp, camera, params)
    thw = thw_from_distance(dist, speed)
    return dist, thw, thw_to_risk(thw)
