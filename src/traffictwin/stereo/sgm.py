"""Semi-global matching disparity (docs/design.md "SGM"; paper 003 section 3.3).

OpenCV ``StereoSGBM`` in full 8-path mode (``STEREO_SGBM_MODE_HH``) with the smoothness
penalties ``P1 = 8 * cn * bs**2`` and ``P2 = 32 * cn * bs**2`` (cn = image channels, bs =
block size) and the left-right consistency check ``disp12MaxDiff = 1``. OpenCV returns
fixed-point int16 disparities (x16); we divide by 16 and keep every pixel OpenCV marks
invalid (occlusions, left-right check failures, the left border without a full search
range, uniqueness failures) as ``-1.0``: the map is deliberately non-dense like the paper's.

Speckle filtering is on by default with OpenCV's documented recipe for ``StereoSGBM``
(``speckleWindowSize`` 100 px, ``speckleRange`` 2 px: "50-200" and "1 or 2 is good enough"):
connected blobs of fewer than 100 pixels whose disparity differs from their surroundings by
more than 2 px are marked invalid. It only removes pixels (values elsewhere are unchanged). On
the default data it lowers bad-2 from 2.94 % to 2.16 % of valid pixels (README, stereo
section). OpenCV's ``stereo_match`` sample passes ``speckleRange=32`` instead (OpenCV multiplies
it by 16 internally, so 32 lets almost every blob through: bad-2 2.82 %).

:func:`valid_share` is the GT-free quality statistic of a map: the share of valid pixels in the
columns SGM can match at all (the left ``min_disparity + num_disparities`` columns never can).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np

from traffictwin.config import spec

INVALID = -1.0


@dataclass
class SgmParams:
    """``risk_data.sgm``: search range (px, multiple of 16), block size (px, odd), uniqueness
    ratio, speckle filter (max. blob size px, 0 = off; disparity range px) and whether to match
    on grayscale (cn = 1)."""

    num_disparities: int = spec(min=16)
    block_size: int = spec(min=1)
    uniqueness_ratio: int = spec(min=0)
    speckle_window: int = spec(min=0)
    speckle_range: int = spec(min=0)
    gray: bool = spec()

    def __post_init__(self) -> None:
        self.matcher()  # make_matcher's checks (multiple of 16, odd block), before any work

    def check_width(self, width: int, what: str = "images") -> None:
        """ValueError unless ``width`` px images leave room for this search range and block
        (:func:`check_image_width`)."""
        check_image_width(width, self.num_disparities, self.block_size, what=what)

    def matcher(self) -> cv2.StereoSGBM:
        """The configured ``StereoSGBM`` (see :func:`make_matcher`)."""
        return make_matcher(
            self.num_disparities,
            self.block_size,
            1 if self.gray else 3,
            self.uniqueness_ratio,
            self.speckle_window,
            self.speckle_range,
        )


def check_pair_shapes(left: np.ndarray, right: np.ndarray, what: str = "stereo pair") -> None:
    """Raise ValueError unless ``left`` and ``right`` are uint8 images of identical shape."""
    for name, img in (("left", left), ("right", right)):
        if not isinstance(img, np.ndarray):
            raise ValueError(
                f"{what}: {name} image must be a numpy array, got {type(img).__name__}"
            )
        if (
            img.dtype != np.uint8
            or img.ndim not in (2, 3)
            or (img.ndim == 3 and img.shape[2] not in (1, 3))
        ):
            raise ValueError(
                f"{what}: {name} image must be uint8 (H, W) or (H, W, 3) BGR, got {img.dtype} {img.shape}"
            )
    if left.shape != right.shape:
        raise ValueError(
            f"{what}: left and right images differ in size: {left.shape} vs {right.shape}"
        )


def check_image_width(
    width: int,
    num_disparities: int,
    block_size: int,
    min_disparity: int = 0,
    what: str = "images",
) -> None:
    """OpenCV's StereoSGBM needs ``width - (min_disparity + num_disparities) > block_size // 2``
    (else it refuses the pair: results would be non-deterministic); ValueError naming the sizes."""
    need = int(min_disparity) + int(num_disparities) + int(block_size) // 2
    if int(width) <= need:
        raise ValueError(
            f"{what}: num_disparities={num_disparities} and block_size={block_size} need images "
            f"wider than min_disparity + num_disparities + block_size // 2 = {need} px "
            f"(OpenCV StereoSGBM), got {width} px"
        )


def make_matcher(
    num_disparities: int = 64,
    block_size: int = 5,
    channels: int = 3,
    uniqueness_ratio: int = 10,
    speckle_window: int = 100,
    speckle_range: int = 2,
    min_disparity: int = 0,
) -> cv2.StereoSGBM:
    """A configured ``StereoSGBM`` (num_disparities: search range px, multiple of 16; block_size odd
    px; speckle_window: max. blob size px, 0 = no speckle filter; speckle_range: px)."""
    if num_disparities <= 0 or num_disparities % 16:
        raise ValueError(
            f"sgm num_disparities must be a positive multiple of 16, got {num_disparities}"
        )
    if block_size < 1 or block_size % 2 == 0:
        raise ValueError(f"sgm block_size must be odd and >= 1, got {block_size}")
    cn = int(channels)
    return cv2.StereoSGBM.create(
        minDisparity=int(min_disparity),
        numDisparities=int(num_disparities),
        blockSize=int(block_size),
        P1=8 * cn * block_size**2,
        P2=32 * cn * block_size**2,
        disp12MaxDiff=1,
        uniquenessRatio=int(uniqueness_ratio),
        speckleWindowSize=int(speckle_window),
        speckleRange=int(speckle_range),
        mode=cv2.STEREO_SGBM_MODE_HH,
    )


def compute_disparity(
    left_bgr: np.ndarray,
    right_bgr: np.ndarray,
    num_disparities: int = 64,
    block_size: int = 5,
    uniqueness_ratio: int = 10,
    speckle_window: int = 100,
    speckle_range: int = 2,
    min_disparity: int = 0,
    gray: bool = False,
    matcher: cv2.StereoSGBM | None = None,
) -> np.ndarray:
    """SGM disparity of a rectified pair: float32 (H, W) px, ``-1.0`` where invalid.

    left_bgr/right_bgr: uint8 BGR (or grayscale) images of equal shape; gray: match on
    grayscale (cn = 1) instead of colour (cn = 3). ``matcher`` reuses a prepared matcher.
    """
    check_pair_shapes(left_bgr, right_bgr)
    if gray and left_bgr.ndim == 3:
        left_bgr = cv2.cvtColor(left_bgr, cv2.COLOR_BGR2GRAY)
        right_bgr = cv2.cvtColor(right_bgr, cv2.COLOR_BGR2GRAY)
    cn = 1 if left_bgr.ndim == 2 else left_bgr.shape[2]
    m = matcher or make_matcher(
        num_disparities,
        block_size,
        cn,
        uniqueness_ratio,
        speckle_window,
        speckle_range,
        min_disparity,
    )
    check_image_width(
        left_bgr.shape[1],
        m.getNumDisparities(),
        m.getBlockSize(),
        m.getMinDisparity(),
        what=f"stereo pair {left_bgr.shape[1]}x{left_bgr.shape[0]}",
    )
    raw = m.compute(left_bgr, right_bgr)
    disp = raw.astype(np.float32) / 16.0
    disp[raw < m.getMinDisparity() * 16] = INVALID
    return disp


def disparity_frames(
    left: np.ndarray, right: np.ndarray, params: SgmParams
) -> tuple[np.ndarray, float]:
    """SGM disparity of every pair of the stacks ``left``/``right`` (N, H, W[, 3]) with one matcher:
    (N, H, W) float32 px (``-1.0`` invalid) and the seconds spent matching (timing only)."""
    m = params.matcher()
    out, secs = [], 0.0
    for k in range(len(left)):
        t0 = time.perf_counter()
        out.append(compute_disparity(left[k], right[k], gray=params.gray, matcher=m))
        secs += time.perf_counter() - t0
    return np.stack(out), secs


def valid_share(disp: np.ndarray, num_disparities: int, min_disparity: int = 0) -> np.ndarray:
    """Share of valid pixels (``>= 0``) of SGM maps in the columns SGM can match, i.e. without the
    left ``min_disparity + num_disparities`` columns that OpenCV always leaves invalid.

    ``disp``: (H, W) or (N, H, W) px; returns a float64 scalar array or (N,) shares in [0, 1].
    """
    d = np.asarray(disp)
    band = int(min_disparity) + int(num_disparities)
    if d.ndim not in (2, 3) or band < 0 or band >= d.shape[-1]:
        raise ValueError(
            f"valid_share: need (H, W) or (N, H, W) maps wider than the unmatched band of {band} "
            f"columns, got shape {d.shape}"
        )
    return (d[..., band:] >= 0).mean(axis=(-2, -1))
