"""Disparity through the API: the disparity source a user picks or a risk model reads (OpenCV
SGM, or the learned stereo network loaded by the sealed, weights-only path) and the disparity map
(px, float32, ``-1`` invalid) with its per-pixel confidence of one rectified stereo pair, after
the same input and pair checks as :func:`~traffictwin.api.risk.assess_risk`."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from .errors import ApiError, InputValueError, ModelDomainError
from .inputs import check_path

#: the disparity sources: OpenCV SGM, or the learned stereo network (a model folder)
SGM = "sgm"
#: the dataset key of each source's disparity (what a risk predictor names in ``cfg.inputs``)
SOURCE_KEYS = {"sgm": "disp_sgm", "learned": "disp_learned"}


@dataclass
class LoadedStereo:
    """A disparity source: ``net`` the learned stereo network (``None``: OpenCV SGM) and a
    description of where it came from."""

    net: Any
    description: str

    @property
    def source(self) -> str:
        """``sgm`` or ``learned``."""
        return "sgm" if self.net is None else "learned"

    @property
    def key(self) -> str:
        """The disparity key a risk predictor names for this source (``disp_sgm``, ...)."""
        return SOURCE_KEYS[self.source]

    @property
    def image_size(self) -> tuple[int, int] | None:
        """``(height, width)`` px the network was trained on (``None`` for SGM or unknown)."""
        size = (getattr(self.net, "meta", None) or {}).get("image_size")
        if isinstance(size, (list, tuple)) and len(size) == 2:
            return int(size[0]), int(size[1])
        return None


def load_stereo(model: str | os.PathLike = SGM, *, tracking_uri: str | None = None) -> LoadedStereo:
    """The disparity source ``model``: ``"sgm"`` (OpenCV SGM), a registry reference of the
    learned stereo network (``traffictwin-stereo@champion``; a bare alias means
    ``traffictwin-stereo``), or its folder (``model.ckpt`` + ``model_meta.json`` as
    ``train_stereo`` writes it). Either way the files are checked against their sealed SHA-256
    and read weights-only. Raises :class:`ApiError` naming the file or model."""
    from traffictwin.mlops.registry import STEREO_NAME
    from traffictwin.risk.stereo_io import StereoModelError, load_stereo_model

    from .inputs import check_optional_text
    from .registry import _load_model, _split_ref

    check_path(model, "model", f"'{SGM}', a registry reference name@alias or a stereo model folder")
    check_optional_text(tracking_uri, "tracking_uri")
    if str(model) == SGM:
        return LoadedStereo(None, "SGM (OpenCV StereoSGBM)")
    path = _split_ref(model)[2]
    if path is not None and not path.exists():
        raise ApiError(
            f"{path}: stereo model not found (expected '{SGM}', a registry reference such as "
            f"{STEREO_NAME}@champion, or a folder with model.ckpt and model_meta.json, e.g. "
            "models/stereo/learned)"
        )
    net, desc = _load_model(
        model, load_stereo_model, StereoModelError, "stereo model", STEREO_NAME, tracking_uri
    )
    return LoadedStereo(net, f"learned stereo network {desc}")


def check_stereo_size(stereo: LoadedStereo, width: int, height: int, who: str) -> None:
    """:class:`ModelDomainError` naming ``who`` unless ``width`` x ``height`` px is the size the
    learned network was trained on (SGM takes any size)."""
    size = stereo.image_size
    if size is not None and (height, width) != size:
        raise ModelDomainError(
            f"{who}: image size {width}x{height} differs from the stereo network's training "
            f"images {size[1]}x{size[0]} (W x H, image_size of {stereo.description}; its "
            "disparity is in that camera's pixel scale)"
        )


def disparities(
    stereo: LoadedStereo | None,
    left: np.ndarray,
    right: np.ndarray,
    sgm: np.ndarray,
    batch_size: int = 8,
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], float]:
    """``(disparity by key, confidence by key, network ms per pair)`` of BGR pairs (N, H, W, 3)
    whose SGM disparity ``sgm`` (N, H, W) px is computed: ``disp_sgm`` always, ``disp_learned``
    too when ``stereo`` is the learned network (which refines SGM in its ``base: sgm`` mode)."""
    from traffictwin.risk.stereo_inference import (
        disparity_confidence,
        learned_disparity,
        spread_threshold,
    )

    disp = {"disp_sgm": sgm}
    conf = {"disp_sgm": disparity_confidence(sgm)}
    ms = 0.0
    if stereo is not None and stereo.net is not None:
        t0 = time.perf_counter()
        d, spread = learned_disparity(stereo.net, left, right, sgm=sgm, batch_size=batch_size)
        ms = (time.perf_counter() - t0) * 1e3 / max(len(left), 1)
        disp["disp_learned"] = d
        conf["disp_learned"] = disparity_confidence(d, spread, spread_threshold(stereo.net))
    return disp, conf, ms


@dataclass
class DisparityResult:
    """The disparity of one pair: ``disparity`` (H, W) float32 px (``-1`` invalid),
    ``confidence`` (H, W) float32 in [0, 1] (0 invalid), the ``source`` (``sgm`` / ``learned``)
    and the pair check's result ``check`` (ORB statistics, ``orb_outlier``, ``orb_reason``)."""

    disparity: np.ndarray
    confidence: np.ndarray
    source: str
    check: dict[str, Any]

    @property
    def reliable(self) -> bool:
        """Whether the pair passed its check (else the disparity is not to be trusted)."""
        return not self.check["orb_outlier"]


def disparity_of_pair(
    stereo: LoadedStereo,
    left: str | os.PathLike | np.ndarray,
    right: str | os.PathLike | np.ndarray,
    *,
    params_path: str | os.PathLike | None = None,
    settings: Any = None,
) -> DisparityResult:
    """The disparity map and its confidence of one rectified pair (image paths or BGR uint8
    arrays), after the checks of ``traffictwin risk``: both images readable, of equal size (and
    the learned network's training size), and the ORB pair check, whose result is returned
    (``reliable`` False: the maps are computed from a pair that cannot be trusted). SGM settings:
    ``settings`` (:class:`~traffictwin.api.StereoSettings`), else ``risk_data.sgm`` / ``orb`` of
    ``params_path``, else the library defaults."""
    from traffictwin.stereo.orb import check_pair
    from traffictwin.stereo.sgm import compute_disparity

    from .images import Frame
    from .pairs import StereoSettings, _pair_images, orb_fields, stereo_settings

    if not isinstance(stereo, LoadedStereo):
        raise InputValueError(
            f"stereo: expected api.LoadedStereo (api.load_stereo), got {type(stereo).__name__}"
        )
    if settings is not None and not isinstance(settings, StereoSettings):
        raise InputValueError("settings: expected api.StereoSettings or None")
    st = settings or stereo_settings(None, params_path)
    l_img, r_img = _pair_images(Frame("pair", left, right), None, "", False)
    check_stereo_size(stereo, l_img.shape[1], l_img.shape[0], "left image")
    orb = check_pair(l_img, r_img, **st.orb)
    sgm = compute_disparity(l_img, r_img, **st.sgm)
    disp, conf, _ = disparities(stereo, l_img[None], r_img[None], sgm[None])
    return DisparityResult(disp[stereo.key][0], conf[stereo.key][0], stereo.source, orb_fields(orb))
