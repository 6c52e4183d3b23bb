"""Stereo images for the API: size checks from the file header (px), reading as 8-bit BGR, and
the ``<id>_left`` / ``<id>_right`` pairs of a folder."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .errors import ApiError, InputFileError, InputValueError
from .inputs import check_path

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm")
MIN_IMAGE_PX = 32  # the smallest image side (px) SGM and the ORB check can work on
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"  # the first 8 bytes of every PNG file


def check_image_file(path: str | os.PathLike) -> tuple[int, int]:
    """``(width, height)`` (px) of an image file from its header alone: :class:`InputFileError`
    when it is missing, not a supported format or larger than the pixel limit. Cheap (nothing is
    decoded): the CLI checks every input this way before it loads a model."""
    from traffictwin.io.limits import InputError, check_image_size

    path = Path(check_path(path, "path"))
    if not path.is_file():
        raise InputFileError(f"{path}: image not found")
    try:  # format and size from the header, before a pixel is decoded
        return check_image_size(path)
    except InputError as exc:
        raise InputFileError(str(exc)) from None


def read_image(path: str | os.PathLike) -> np.ndarray:
    """An 8-bit BGR image (grayscale is expanded to 3 channels, :func:`as_bgr`); errors name the file."""
    import cv2

    path = Path(check_path(path, "path"))
    check_image_file(path)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputFileError(f"{path}: not a readable image (OpenCV could not decode it)")
    return as_bgr(img, str(path))


def decode_png(data: bytes, who: str) -> np.ndarray:
    """An 8-bit BGR image (:func:`as_bgr`) from the bytes of a PNG file (``who`` names them in
    errors): :class:`InputValueError` when they are not a PNG, its header says more pixels than
    the pixel limit (checked before a pixel is decoded), or OpenCV cannot decode them."""
    import io

    import cv2

    from traffictwin.io.limits import _png_size, max_image_pixels

    if not isinstance(data, (bytes, bytearray)):
        raise InputValueError(f"{who}: expected the bytes of a PNG file, got {type(data).__name__}")
    if not data.startswith(PNG_SIGNATURE):
        raise InputValueError(
            f"{who}: not a PNG ({len(data)} bytes without the PNG signature); expected a PNG "
            "file's bytes"
        )
    try:
        w, h = _png_size(io.BytesIO(data))
    except ValueError as exc:
        raise InputValueError(f"{who}: not a readable PNG ({exc})") from None
    if w * h > max_image_pixels():
        raise InputValueError(
            f"{who}: PNG of {w}x{h} px (W x H), more than the limit of {max_image_pixels():,} "
            "pixels"
        )
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputValueError(
            f"{who}: not a decodable PNG (OpenCV could not decode its {len(data)} bytes)"
        )
    return as_bgr(img, who)


@dataclass
class Frame:
    """One stereo pair: an id and the left/right images as paths (read when their batch comes)
    or as BGR uint8 arrays."""

    id: str
    left: str | os.PathLike | np.ndarray
    right: str | os.PathLike | np.ndarray

    def __post_init__(self) -> None:
        """:class:`InputValueError` naming the field unless ``id`` is a string and each image a
        path or an array (the array's dtype and shape are checked when it is used)."""
        if not isinstance(self.id, str):
            raise InputValueError(f"Frame id: expected a string, got {type(self.id).__name__}")
        for side in ("left", "right"):
            v = getattr(self, side)
            if not isinstance(v, np.ndarray):
                check_path(v, f"frame {self.id!r} {side}", "an image path or a uint8 array")


def frames_in_folder(folder: str | os.PathLike) -> list[Frame]:
    """A :class:`Frame` for every ``<id>_left.<ext>`` / ``<id>_right.<ext>`` in ``folder``
    (sorted by id; nothing decoded). Errors on a folder without pairs and on an image without
    its partner."""
    folder = Path(check_path(folder, "folder"))
    if not folder.is_dir():
        raise InputFileError(
            f"{folder}: {'not a folder' if folder.exists() else 'folder not found'} "
            "(expected a folder of <id>_left.png / <id>_right.png pairs)"
        )
    lefts, rights = {}, {}
    for p in sorted(folder.iterdir()):
        if not p.is_file() or p.suffix.lower() not in IMAGE_EXTS:
            continue
        if p.stem.endswith("_left"):
            lefts[p.stem[: -len("_left")]] = p
        elif p.stem.endswith("_right"):
            rights[p.stem[: -len("_right")]] = p
    lonely = sorted(set(lefts) ^ set(rights))
    if lonely:
        k = lonely[0]
        have = lefts.get(k) or rights.get(k)
        want = "_right" if k in lefts else "_left"
        raise ApiError(
            f"{have}: no partner image '{k}{want}.*' in {folder} ({len(lonely)} unpaired image(s))"
        )
    if not lefts:
        raise ApiError(f"{folder}: no stereo pairs found (expected <id>_left.png / <id>_right.png)")
    return [Frame(k, lefts[k], rights[k]) for k in sorted(lefts)]


def as_bgr(img: Any, who: str) -> np.ndarray:
    """An 8-bit BGR ``(H, W, 3)`` image from an 8-bit grayscale ``(H, W)``, ``(H, W, 1)``, BGR or
    BGRA array; :class:`InputValueError` naming ``who`` otherwise (dtype, shape, too small)."""
    import cv2

    a = np.asarray(img)
    if a.dtype != np.uint8:
        raise InputValueError(f"{who}: expected an 8-bit (uint8) image, got dtype {a.dtype}")
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim == 2:
        a = cv2.cvtColor(a, cv2.COLOR_GRAY2BGR)
    elif a.ndim == 3 and a.shape[2] == 4:
        a = cv2.cvtColor(a, cv2.COLOR_BGRA2BGR)
    elif a.ndim != 3 or a.shape[2] != 3:
        raise InputValueError(
            f"{who}: expected a grayscale (H, W), BGR (H, W, 3) or BGRA (H, W, 4) image, got shape {a.shape}"
        )
    if min(a.shape[:2]) < MIN_IMAGE_PX:
        raise InputValueError(
            f"{who}: image {a.shape[1]}x{a.shape[0]} px (W x H) is smaller than {MIN_IMAGE_PX} px "
            "on a side; stereo matching needs a real camera image"
        )
    return np.ascontiguousarray(a)
