"""Classical grid-map registration: the `registered` baseline's pose correction.

Given map 1, map 2 (each in its own sensor frame) and the *noisy* relative pose of map 2's
sensor in map 1's frame, estimate a better relative pose from the maps themselves:

1. **Prealign.** Warp map 2's feature image (default: ``m_O`` — on lidar maps the free-space
   fans are centred on each sensor and mislead the matching, occupancy is the shared structure)
   into map 1's frame with the noisy pose.
2. **Coarse rotation** (Fourier–Mellin): magnitude spectra of both (square-padded, Hann-windowed,
   high-pass filtered) feature images are translation invariant; in log-polar coordinates
   a rotation is a cyclic shift along the angle axis, found by phase correlation. The spectrum is
   point symmetric, so the angle is known modulo 180°; the candidate in [−90°, 90°) is kept, and
   the prior (0°, i.e. trust the noisy pose) is always a candidate too. With partially
   overlapping maps the spectrum's angle is often wrong, so a grid of angles in
   ``±max_rot_deg`` (``search_step_deg``, default 2°) is tried as well.
3. **Coarse translation**: for each candidate angle, rotate and phase-correlate with the shift
   searched within ``max_trans_m`` only (:class:`BoundedPhaseCorrelator`, same convention as
   ``cv2.phaseCorrelate`` but zero-padded and bounded: the unbounded peak often locks onto the
   edges of the maps' known areas); the candidate with the best masked correlation wins.
4. **Refinement**: ``cv2.findTransformECCWithMask`` (``MOTION_EUCLIDEAN``) in the prealigned
   frame, restricted to cells known in both maps, started from the coarse estimate. (OpenCV's
   Euclidean ECC recovers its angle with ``asin``, so it only works for |rotation| < 90°: the
   often ~180° relative yaw of oncoming vehicles stays in the prealignment.)
5. **Fallback**: the estimate is accepted only if its masked correlation beats the noisy pose's by
   more than ``min_gain``, reaches ``min_cc`` and the correction stays within ``max_trans_m`` /
   ``max_rot_deg``; otherwise the noisy pose is returned (``accepted = False``).

Geometry (docs/design.md grid convention): cell (row v, col u) has its centre at
``x = (H/2 − v − 0.5)·cell``, ``y = (W/2 − u − 0.5)·cell``. With ``P`` the metric → pixel map and
``T`` the SE(2) matrix of the relative pose (map-2 frame → map-1 frame), the pixel transform
map 2 → map 1 is ``A = P T P⁻¹``. ``P`` swaps and negates axes, so a metric yaw ``+ψ`` is a pixel
rotation of ``−ψ`` — the code composes matrices and never reasons about angle signs.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np

from traffictwin.evidential.warp import pixel_from_metric
from traffictwin.geometry import se2_matrix
from traffictwin.grid import GridSpec

__all__ = [
    "RegistrationParams",
    "RegistrationResult",
    "pose_to_pixel_affine",
    "pixel_affine_to_pose",
    "feature_image",
    "known_mask",
    "warp_image",
    "register_pair",
    "ecc_align",
    "masked_cc",
    "PairFeatures",
    "pair_features",
    "scored_estimate",
    "BoundedPhaseCorrelator",
    "pose_error",
]

FEATURES = ("occ", "signed", "pignistic")


@dataclass(frozen=True)
class RegistrationParams:
    """Settings of :func:`register_pair` (units in the names: m, deg, cells)."""

    feature: str = "occ"  # occ: m_O; signed: m_O − m_F; pignistic: p_O − 0.5
    known_threshold: float = 0.05  # a cell is "known" where m_F + m_O > this
    blur_sigma_cells: float = 1.0  # Gaussian blur of the feature images before the coarse step
    n_angles: int = 720  # angle bins of the log-polar spectrum (0.5° each at 720)
    search_step_deg: float = (
        2.0  # > 0 adds a grid of candidate angles in [−max_rot_deg, max_rot_deg]
    )
    ecc_iterations: int = 60
    ecc_eps: float = 1e-5
    ecc_gauss_size: int = 5  # OpenCV's blur inside ECC (odd, cells)
    ecc_levels: int = 1  # ECC pyramid levels (1 = full resolution only; each further level halves)
    min_cc: float = 0.2  # minimum masked correlation coefficient of an accepted estimate
    min_gain: float = (
        0.02  # the estimate's correlation must exceed the noisy pose's by more than this
    )
    max_trans_m: float = 10.0  # largest accepted correction of the translation (m)
    max_rot_deg: float = 30.0  # largest accepted correction of the yaw (deg)
    min_overlap: float = 0.05  # minimum fraction of cells known in both maps for a usable score

    def __post_init__(self) -> None:
        if self.feature not in FEATURES:
            raise ValueError(
                f"RegistrationParams.feature must be one of {FEATURES}, got {self.feature!r}"
            )
        if self.n_angles < 36:
            raise ValueError(f"RegistrationParams.n_angles must be >= 36, got {self.n_angles}")
        if self.ecc_gauss_size < 1 or self.ecc_gauss_size % 2 == 0:
            raise ValueError(
                f"RegistrationParams.ecc_gauss_size must be a positive odd integer, got {self.ecc_gauss_size}"
            )
        for name in ("ecc_iterations", "ecc_levels", "max_trans_m", "max_rot_deg"):
            if getattr(self, name) <= 0:
                raise ValueError(
                    f"RegistrationParams.{name} must be > 0, got {getattr(self, name)}"
                )


@dataclass
class RegistrationResult:
    """Outcome of :func:`register_pair`.

    pose: the relative pose used (x m, y m, yaw rad) — the estimate if accepted, else the noisy
    pose; accepted: whether the estimate passed the checks; cc_noisy / cc_est: masked correlation
    of the feature images under the noisy pose / the estimate; coarse_deg: the chosen coarse pixel
    rotation; ecc_ok: ECC converged; seconds: wall time.
    """

    pose: np.ndarray
    accepted: bool
    cc_noisy: float
    cc_est: float
    coarse_deg: float
    ecc_ok: bool
    seconds: float
    estimate: np.ndarray  # the (possibly rejected) estimate


# -- geometry -----------------------------------------------------------------------------------
def pose_to_pixel_affine(rel_pose: np.ndarray, grid: GridSpec) -> np.ndarray:
    """3×3 pixel transform map-2 pixel → map-1 pixel for ``rel_pose`` (x m, y m, yaw rad)."""
    p = pixel_from_metric(grid)
    return p @ se2_matrix(*(float(v) for v in rel_pose)) @ np.linalg.inv(p)


def pixel_affine_to_pose(a: np.ndarray, grid: GridSpec) -> np.ndarray:
    """Inverse of :func:`pose_to_pixel_affine` (the rotation part is re-orthonormalised)."""
    p = pixel_from_metric(grid)
    t = np.linalg.inv(p) @ np.asarray(a, dtype=np.float64) @ p
    yaw = np.arctan2(t[1, 0] - t[0, 1], t[0, 0] + t[1, 1])
    return np.array([t[0, 2], t[1, 2], yaw])


def pose_error(est: np.ndarray, true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation (m) and absolute yaw (deg) error between pose arrays (…, 3)."""
    est = np.asarray(est, dtype=np.float64)
    true = np.asarray(true, dtype=np.float64)
    dt = np.hypot(est[..., 0] - true[..., 0], est[..., 1] - true[..., 1])
    dyaw = np.angle(np.exp(1j * (est[..., 2] - true[..., 2])))
    return dt, np.degrees(np.abs(dyaw))


# -- images -------------------------------------------------------------------------------------
def feature_image(m: np.ndarray, kind: str = "signed") -> np.ndarray:
    """Single-channel float32 image (H, W) of masses ``m`` (2, H, W) used for matching."""
    m = np.asarray(m, dtype=np.float32)
    if m.ndim != 3 or m.shape[0] != 2:
        raise ValueError(f"feature_image: expected masses (2,H,W), got shape {m.shape}")
    if kind == "occ":
        return np.ascontiguousarray(m[1])
    if kind == "signed":
        return np.ascontiguousarray(m[1] - m[0])
    if kind == "pignistic":
        return np.ascontiguousarray(m[1] + 0.5 * (1 - m[0] - m[1]) - 0.5)
    raise ValueError(f"feature_image: kind must be one of {FEATURES}, got {kind!r}")


def known_mask(m: np.ndarray, threshold: float = 0.05) -> np.ndarray:
    """uint8 mask (H, W): 255 where ``m_F + m_O > threshold``."""
    m = np.asarray(m)
    return ((m[0] + m[1]) > threshold).astype(np.uint8) * 255


def warp_image(
    img: np.ndarray, a: np.ndarray, shape: tuple[int, int], nearest: bool = False
) -> np.ndarray:
    """Warp ``img`` forward with the 3×3 pixel transform ``a`` (src pixel → dst pixel); outside → 0."""
    flags = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    return cv2.warpAffine(
        img,
        np.ascontiguousarray(a[:2], dtype=np.float64),
        (shape[1], shape[0]),
        flags=flags,
        borderValue=0,
    )


def masked_cc(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    """Zero-mean normalised correlation of ``a`` and ``b`` over ``mask`` (bool); −1 if undefined."""
    n = int(mask.sum())
    if n < 16:
        return -1.0
    x = a[mask].astype(np.float64)
    y = b[mask].astype(np.float64)
    x -= x.mean()
    y -= y.mean()
    d = np.sqrt((x * x).sum() * (y * y).sum())
    return float((x * y).sum() / d) if d > 0 else -1.0


def _pad_square(img: np.ndarray, size: int) -> np.ndarray:
    h, w = img.shape
    out = np.zeros((size, size), np.float32)
    r0, c0 = (size - h) // 2, (size - w) // 2
    out[r0 : r0 + h, c0 : c0 + w] = img
    return out


def _log_polar_spectrum(img: np.ndarray, n_angles: int) -> np.ndarray:
    """High-pass filtered log magnitude spectrum of ``img`` (square) in log-polar coordinates (angles × radii)."""
    s = img.shape[0]
    win = cv2.createHanningWindow((s, s), cv2.CV_32F)
    spec = np.fft.fftshift(np.abs(np.fft.fft2(img * win)))
    f = np.fft.fftshift(np.fft.fftfreq(s))
    fx, fy = np.meshgrid(f, f)
    hp = (1.0 - np.cos(np.pi * fx) * np.cos(np.pi * fy)) * (
        2.0 - np.cos(np.pi * fx) * np.cos(np.pi * fy)
    )
    mag = (np.log1p(spec) * hp).astype(np.float32)
    radius = s / 2
    return cv2.warpPolar(
        mag, (s // 2, n_angles), (s / 2, s / 2), radius, cv2.WARP_POLAR_LOG | cv2.INTER_LINEAR
    )


def _fourier_mellin_angle(f1: np.ndarray, g2: np.ndarray, n_angles: int) -> float:
    """Pixel-space rotation (deg, in (−90, 90]) such that rotating by it (getRotationMatrix2D,
    inverse map) brings ``g2`` onto ``f1``'s orientation."""
    s = int(max(f1.shape))
    lp1 = _log_polar_spectrum(_pad_square(f1, s), n_angles)
    lp2 = _log_polar_spectrum(_pad_square(g2, s), n_angles)
    (_, dy), _ = cv2.phaseCorrelate(lp1.astype(np.float64), lp2.astype(np.float64))
    ang = dy * 360.0 / n_angles
    ang = (ang + 90.0) % 180.0 - 90.0  # modulo 180 (point-symmetric spectrum), into [−90, 90)
    return float(-ang)


class BoundedPhaseCorrelator:
    """Phase correlation against a fixed image ``a`` with the shift searched only within a radius.

    Like ``cv2.phaseCorrelate`` (same sign convention: ``b(p + s) ≈ a(p)``, Hann window) but
    zero-padded by the search radius so shifts do not wrap around, with the peak restricted to
    ``|s| ≤ max_shift_px`` (partially overlapping grid maps otherwise often lock onto the edges of
    their known areas), and with ``a``'s spectrum computed once for many ``b``. Sub-pixel
    refinement: 3-point parabola per axis.
    """

    def __init__(self, a: np.ndarray, max_shift_px: float) -> None:
        from scipy import fft

        self._fft = fft
        h, w = a.shape
        pad = int(np.ceil(max_shift_px)) + 2
        self.size = (cv2.getOptimalDFTSize(h + pad), cv2.getOptimalDFTSize(w + pad))
        self.win = cv2.createHanningWindow((w, h), cv2.CV_32F)
        self.fa_conj = np.conj(fft.rfft2(a.astype(np.float32) * self.win, s=self.size))
        hh, ww = self.size
        self.dy = np.fft.fftfreq(hh, 1.0 / hh)
        self.dx = np.fft.fftfreq(ww, 1.0 / ww)
        self.outside = (self.dx[None, :] ** 2 + self.dy[:, None] ** 2) > max_shift_px**2

    def shift(self, b: np.ndarray) -> tuple[float, float, float]:
        """``(sx, sy, peak)``: the shift (px) and the height of the correlation peak (≤ 1)."""
        fft = self._fft
        cross = fft.rfft2(b.astype(np.float32) * self.win, s=self.size) * self.fa_conj
        cross /= np.maximum(np.abs(cross), 1e-12)
        r = fft.irfft2(cross, s=self.size)
        r[self.outside] = -np.inf
        hh, ww = self.size
        iy, ix = np.unravel_index(int(np.argmax(r)), r.shape)

        def parabola(c_m: float, c_0: float, c_p: float) -> float:
            if not (np.isfinite(c_m) and np.isfinite(c_p)):
                return 0.0
            d = c_m - 2 * c_0 + c_p
            return float(0.5 * (c_m - c_p) / d) if d < 0 else 0.0

        oy = parabola(r[(iy - 1) % hh, ix], r[iy, ix], r[(iy + 1) % hh, ix])
        ox = parabola(r[iy, (ix - 1) % ww], r[iy, ix], r[iy, (ix + 1) % ww])
        return float(self.dx[ix] + ox), float(self.dy[iy] + oy), float(r[iy, ix])


def _rot(center: tuple[float, float], deg: float) -> np.ndarray:
    return np.vstack([cv2.getRotationMatrix2D(center, deg, 1.0), [0.0, 0.0, 1.0]])


def _coarse_alignment(
    f1: np.ndarray,
    g2: np.ndarray,
    k1: np.ndarray,
    kg2: np.ndarray,
    grid: GridSpec,
    params: RegistrationParams,
) -> tuple[np.ndarray, float]:
    """The coarse step of :func:`register_pair`: Fourier–Mellin rotation (+ prior 0, + optional
    grid of angles), phase-correlation translation; the best ``(W: map1 px → prealigned px (3, 3),
    angle deg)`` by masked correlation of the (blurred) features ``f1`` and prealigned ``g2``."""
    shape = grid.shape
    if params.blur_sigma_cells > 0:
        b1 = cv2.GaussianBlur(f1, (0, 0), params.blur_sigma_cells)
        b2 = cv2.GaussianBlur(g2, (0, 0), params.blur_sigma_cells)
    else:
        b1, b2 = f1, g2
    b1 = b1 * (k1 > 0)
    b2 = b2 * (kg2 > 0)
    center = ((shape[1] - 1) / 2.0, (shape[0] - 1) / 2.0)
    cands = {0.0, round(_fourier_mellin_angle(b1, b2, params.n_angles), 3)}
    if params.search_step_deg > 0:
        cands |= set(
            np.round(
                np.arange(-params.max_rot_deg, params.max_rot_deg + 1e-9, params.search_step_deg), 3
            ).tolist()
        )
    pc = BoundedPhaseCorrelator(b1, params.max_trans_m / grid.cell)
    best = (-2.0, np.eye(3), 0.0)  # (cc, W: map1 px → prealigned px, angle)
    size = (shape[1], shape[0])
    for ang in sorted(cands):
        if abs(ang) > params.max_rot_deg:
            continue
        r = _rot(center, ang)  # g2r(p) = g2(R p)
        g2r = cv2.warpAffine(b2, r[:2], size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
        sx, sy, _ = pc.shift(g2r)
        w = r @ np.array([[1.0, 0.0, sx], [0.0, 1.0, sy], [0.0, 0.0, 1.0]])  # g2(W p) ≈ f1(p)
        warped = cv2.warpAffine(b2, w[:2], size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
        kw = cv2.warpAffine(kg2, w[:2], size, flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP)
        cc = masked_cc(b1, warped, (k1 > 0) & (kw > 0))
        if cc > best[0]:
            best = (cc, w, ang)
    _, wc, coarse = best
    return wc, coarse


def _pyramid_scale(level: int) -> np.ndarray:
    """3×3 map full-resolution pixel → pixel of pyramid ``level`` (``cv2.INTER_AREA`` halvings:
    cell centres at integers, ``p_l = (p + ½)/2^l − ½``)."""
    s = 2.0**level
    return np.array([[1 / s, 0.0, 0.5 / s - 0.5], [0.0, 1 / s, 0.5 / s - 0.5], [0.0, 0.0, 1.0]])


def ecc_align(
    f1: np.ndarray,
    g2: np.ndarray,
    k1: np.ndarray,
    kg2: np.ndarray,
    w0: np.ndarray,
    iterations: int,
    eps: float,
    gauss_size: int,
    levels: int = 1,
) -> tuple[np.ndarray, bool]:
    """ECC alignment (``cv2.findTransformECCWithMask``, ``MOTION_EUCLIDEAN``) of image ``g2``
    onto the template ``f1`` (float32 (H, W); masks ``k1``/``kg2`` uint8, 255 = known), started
    from ``w0`` (3×3, template pixel → ``g2`` pixel: ``g2(W p) ≈ f1(p)``).

    ``levels`` > 1: coarse to fine over an image pyramid (each level halves the resolution; the
    estimate of a level starts the next). A level where ECC fails keeps the estimate it was
    given. Returns ``(W (3, 3), converged at full resolution)``; ``w0`` when ECC fails there.
    (OpenCV's Euclidean ECC recovers its angle with ``asin``: |rotation| < 90° only.)
    """
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, int(iterations), float(eps))
    w = np.asarray(w0, dtype=np.float64)
    h, wd = f1.shape
    ok = False
    for level in range(int(levels) - 1, -1, -1):
        if level > 0:
            size = (max(8, wd >> level), max(8, h >> level))
            imgs = [cv2.resize(a, size, interpolation=cv2.INTER_AREA) for a in (f1, g2)]
            masks = [cv2.resize(a, size, interpolation=cv2.INTER_NEAREST) for a in (k1, kg2)]
        else:
            imgs, masks = [f1, g2], [k1, kg2]
        s = _pyramid_scale(level)
        wl = np.ascontiguousarray((s @ w @ np.linalg.inv(s))[:2], dtype=np.float32)
        try:
            _, wl = cv2.findTransformECCWithMask(
                imgs[0],
                imgs[1],
                masks[0],
                masks[1],
                wl,
                cv2.MOTION_EUCLIDEAN,
                criteria,
                int(gauss_size),
            )
        except cv2.error:
            ok = False  # keep the estimate this level was given
            continue
        w = np.linalg.inv(s) @ np.vstack([wl.astype(np.float64), [0.0, 0.0, 1.0]]) @ s
        ok = level == 0
    return w, ok


@dataclass
class PairFeatures:
    """Both maps' feature images and known masks, map 2's warped into map 1's pixels by a pose."""

    f1: np.ndarray
    f2: np.ndarray
    k1: np.ndarray
    k2: np.ndarray
    a0: np.ndarray  # map2 px → map1 px under the pose
    g2: np.ndarray  # map 2's feature image under a0
    kg2: np.ndarray  # map 2's known mask under a0
    both: np.ndarray  # cells known in map 1 and in warped map 2


def pair_features(
    what: str,
    map1: np.ndarray,
    map2: np.ndarray,
    pose: np.ndarray,
    grid: GridSpec,
    feature: str,
    known_threshold: float,
) -> PairFeatures:
    """Shape check (ValueError naming ``what``), feature images, known masks and map 2 warped by
    ``pose`` (x m, y m, yaw rad): the shared start of :func:`register_pair` and
    :func:`~traffictwin.fusion.refinement.refine_pose`."""
    shape = grid.shape
    for name, m in (("map1", map1), ("map2", map2)):
        if np.shape(m) != (2, *shape):
            raise ValueError(
                f"{what}: {name} must have shape (2, {shape[0]}, {shape[1]}), got {np.shape(m)}"
            )
    f1 = feature_image(map1, feature)
    f2 = feature_image(map2, feature)
    k1 = known_mask(map1, known_threshold)
    k2 = known_mask(map2, known_threshold)
    a0 = pose_to_pixel_affine(pose, grid)
    g2 = warp_image(f2, a0, shape)
    kg2 = warp_image(k2, a0, shape, nearest=True)
    return PairFeatures(f1, f2, k1, k2, a0, g2, kg2, (k1 > 0) & (kg2 > 0))


def scored_estimate(
    pf: PairFeatures, a_est: np.ndarray, grid: GridSpec, min_cells: float
) -> tuple[np.ndarray, float]:
    """The pose (x m, y m, yaw rad) of ``a_est`` (map 2 px → map 1 px) and the masked correlation
    of map 1's features with map 2's warped by it (−1 where fewer than ``min_cells`` cells are
    known in both): how :func:`register_pair` and
    :func:`~traffictwin.fusion.refinement.refine_pose` score an estimate."""
    g_est = warp_image(pf.f2, a_est, grid.shape)
    k_est = warp_image(pf.k2, a_est, grid.shape, nearest=True)
    both_est = (pf.k1 > 0) & (k_est > 0)
    cc_est = masked_cc(pf.f1, g_est, both_est) if both_est.sum() >= min_cells else -1.0
    return pixel_affine_to_pose(a_est, grid), cc_est


def register_pair(
    map1: np.ndarray,
    map2: np.ndarray,
    rel_pose_noisy: np.ndarray,
    grid: GridSpec,
    params: RegistrationParams = RegistrationParams(),
) -> RegistrationResult:
    """Estimate the relative pose of map 2's sensor in map 1's frame from the maps (see module doc).

    ``map1``, ``map2``: masses (2, H, W), each in its own sensor frame; ``rel_pose_noisy``:
    (x m, y m, yaw rad) prior; ``grid``: geometry of both maps.
    """
    t0 = time.perf_counter()
    noisy = np.asarray(rel_pose_noisy, dtype=np.float64).reshape(3)
    pf = pair_features(
        "register_pair", map1, map2, noisy, grid, params.feature, params.known_threshold
    )
    f1, k1, a0, g2, kg2, both = pf.f1, pf.k1, pf.a0, pf.g2, pf.kg2, pf.both
    cc_noisy = masked_cc(f1, g2, both)
    min_cells = params.min_overlap * f1.size

    def result(
        est: np.ndarray, accepted: bool, cc_est: float, coarse: float, ecc_ok: bool
    ) -> RegistrationResult:
        return RegistrationResult(
            pose=est if accepted else noisy,
            accepted=accepted,
            cc_noisy=cc_noisy,
            cc_est=cc_est,
            coarse_deg=coarse,
            ecc_ok=ecc_ok,
            seconds=time.perf_counter() - t0,
            estimate=est,
        )

    if both.sum() < min_cells:
        return result(noisy.copy(), False, cc_noisy, 0.0, False)

    wc, coarse = _coarse_alignment(f1, g2, k1, kg2, grid, params)
    wc, ecc_ok = ecc_align(
        f1,
        g2,
        k1,
        kg2,
        wc,
        params.ecc_iterations,
        params.ecc_eps,
        params.ecc_gauss_size,
        params.ecc_levels,
    )
    w_total = np.linalg.inv(a0) @ wc  # map1 px → map2 px
    est, cc_est = scored_estimate(pf, np.linalg.inv(w_total), grid, min_cells)
    dt, dr = pose_error(est, noisy)
    ok = bool(
        cc_est >= params.min_cc
        and cc_est > cc_noisy + params.min_gain
        and dt <= params.max_trans_m
        and dr <= params.max_rot_deg
    )
    return result(est, ok, cc_est, coarse, ecc_ok)
