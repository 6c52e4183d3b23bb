"""A stereo pair's inputs for the API, shared by risk and disparity: the images (read, equal
sizes, the training camera's size or resized to it), the SGM / ORB settings they are matched and
checked with, and the pair check's result as row fields."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from traffictwin.io.outputs import check_regular_file

from .errors import ApiError, InputFileError, InputValueError, ModelDomainError
from .images import Frame, as_bgr, read_image
from .inputs import check_path
from .registry import _first_line

MAX_UPSCALE = 4.0  # resize=True enlarges an image at most this much (per axis) to the camera


def _settings_problem(values: Any, func: Any, skip: tuple[str, ...]) -> str | None:
    """Why ``values`` are not keyword settings of ``func`` (unknown key or a value whose type
    is not its default's), or None."""
    import inspect

    if not isinstance(values, dict):
        return f"expected a mapping of settings, got {type(values).__name__}"
    params = {
        k: p.default
        for k, p in inspect.signature(func).parameters.items()
        if k not in skip and p.default is not inspect.Parameter.empty
    }
    for k, v in values.items():
        if k not in params:
            return f"unknown setting {k!r} (expected from {sorted(params)})"
        d = params[k]
        ok = (
            isinstance(v, bool)
            if isinstance(d, bool)
            else isinstance(v, str)
            if isinstance(d, str)
            else isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
            if isinstance(d, (int, float))
            else True
        )
        if not ok:
            return f"setting {k!r} = {v!r} is not a {type(d).__name__}"
    return None


@dataclass
class StereoSettings:
    """SGM / ORB keyword settings and where they came from."""

    sgm: dict[str, Any]
    orb: dict[str, Any]
    source: str

    def __post_init__(self) -> None:
        """:class:`InputValueError` naming the field unless ``sgm`` / ``orb`` are keyword
        settings of the SGM matcher / the ORB check (known keys, values of their defaults'
        types) and ``source`` a string."""
        from traffictwin.stereo.orb import check_pair
        from traffictwin.stereo.sgm import compute_disparity

        for key, func in (("sgm", compute_disparity), ("orb", check_pair)):
            why = _settings_problem(getattr(self, key), func, ("left_bgr", "right_bgr", "matcher"))
            if why:
                raise InputValueError(f"StereoSettings.{key}: {why}")
        if not isinstance(self.source, str):
            raise InputValueError(
                f"StereoSettings.source: expected a string, got {type(self.source).__name__}"
            )


def _params_risk_data(params_path: str | os.PathLike) -> dict[str, Any]:
    import yaml

    path = Path(check_path(params_path, "params_path"))
    try:
        check_regular_file(path, "a params.yaml")  # stat before open: a FIFO never blocks
    except FileNotFoundError:
        raise InputFileError(f"params_path: {path} not found (expected a params.yaml)") from None
    except OSError as exc:
        raise InputFileError(f"params_path: {path} {exc.strerror or exc}") from None
    try:
        cfg = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise InputFileError(f"{path}: not valid YAML ({_first_line(exc)})") from None
    if not isinstance(cfg, dict):
        raise InputFileError(
            f"{path}: expected a YAML mapping of parameters, got {type(cfg).__name__}"
        )
    rd = cfg.get("risk_data") if isinstance(cfg, dict) else None
    return rd if isinstance(rd, dict) else {}


def stereo_settings(
    domain: Any, params_path: str | os.PathLike | None, model_desc: str = "the model"
) -> StereoSettings:
    """SGM/ORB settings the risk data were made with: ``domain.sgm`` / ``domain.orb`` of the
    model's metadata if present; else ``risk_data.sgm`` / ``risk_data.orb`` of the params file
    ``params_path``; else the library defaults. A given ``params_path`` is always read and
    checked (a missing or invalid file is an error, never ignored)."""
    rd_given = _params_risk_data(params_path) if params_path is not None else None
    if isinstance(domain, dict) and (
        isinstance(domain.get("sgm"), dict) or isinstance(domain.get("orb"), dict)
    ):
        return StereoSettings(
            dict(domain.get("sgm") or {}),
            dict(domain.get("orb") or {}),
            f"metadata of {model_desc}",
        )
    if rd_given is not None:
        rd = rd_given
        if isinstance(rd.get("sgm"), dict) or isinstance(rd.get("orb"), dict):
            return StereoSettings(
                dict(rd.get("sgm") or {}), dict(rd.get("orb") or {}), str(params_path)
            )
    return StereoSettings({}, {}, "library defaults")


def _pair_images(
    fr: Frame, cam: dict[str, Any] | None, description: str, resize: bool
) -> tuple[np.ndarray, np.ndarray]:
    """The BGR images of ``fr`` (read if paths): equal sizes, and the size of the training
    camera ``cam`` (``width`` / ``height`` px of ``description``'s domain) unless ``resize``
    resizes both to it (at most :data:`MAX_UPSCALE` x enlarged). Errors name the image."""
    import cv2

    ln, rn = (
        str(x) if not isinstance(x, np.ndarray) else f"frame {fr.id!r} {side}"
        for x, side in ((fr.left, "left"), (fr.right, "right"))
    )
    left = as_bgr(fr.left if isinstance(fr.left, np.ndarray) else read_image(fr.left), ln)
    right = as_bgr(fr.right if isinstance(fr.right, np.ndarray) else read_image(fr.right), rn)
    if left.shape != right.shape:
        raise ApiError(
            f"{rn}: size {right.shape[1]}x{right.shape[0]} differs from {ln}'s "
            f"{left.shape[1]}x{left.shape[0]} (W x H)"
        )
    if isinstance(cam, dict) and "width" in cam and "height" in cam:
        cw, ch = int(cam["width"]), int(cam["height"])
        if (left.shape[1], left.shape[0]) != (cw, ch):
            if not resize:
                raise ModelDomainError(
                    f"{ln}: image size {left.shape[1]}x{left.shape[0]} differs from the model's "
                    f"training camera {cw}x{ch} (W x H, domain.camera of {description}); "
                    "resize=True (--resize) resizes both images to it (disparity then in the "
                    "camera's pixel scale)"
                )
            up = max(cw / left.shape[1], ch / left.shape[0])
            if up > MAX_UPSCALE:
                raise ModelDomainError(
                    f"{ln}: image {left.shape[1]}x{left.shape[0]} px would be enlarged {up:.1f}x "
                    f"to the training camera {cw}x{ch}; resizing enlarges at most "
                    f"{MAX_UPSCALE:g}x (a smaller image holds too little detail for stereo matching)"
                )
            left = cv2.resize(left, (cw, ch), interpolation=cv2.INTER_AREA)
            right = cv2.resize(right, (cw, ch), interpolation=cv2.INTER_AREA)
    return left, right


def orb_fields(orb: Any) -> dict[str, Any]:
    """The pair check's result as row fields (``orb_outlier``, ``orb_verdict``, ``orb_reason``,
    match counts, mean / median offsets px) of :func:`traffictwin.stereo.orb.check_pair`'s ``orb``."""
    return {
        "orb_outlier": bool(orb.outlier),
        "orb_verdict": "unreliable pair" if orb.outlier else "ok",
        "orb_reason": orb.reason,
        "orb_n_matches": int(orb.n_matches),
        "orb_n_reliable": int(orb.n_reliable),
        "orb_mean_dx": float(orb.mean_dx),
        "orb_mean_dy": float(orb.mean_dy),
        "orb_median_dx": float(orb.median_dx),
    }
