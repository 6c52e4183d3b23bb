"""Risk through the API: load a risk model and check its training domain (camera px, speed range
m/s, SGM / ORB settings), THW verdicts (s) and the streamed assessment of stereo frames."""

from __future__ import annotations

import math
import os
import time
import warnings
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from traffictwin.risk.evaluation.scoring import PAPER
from traffictwin.risk.metric import risk_to_thw
from traffictwin.risk.predictor import PACKAGED_STEREO

from .errors import ApiError, ApiWarning, InputValueError, ModelDomainError
from .images import Frame
from .inputs import (
    _chunks,
    check_count,
    check_flag,
    check_instance,
    check_optional_text,
    check_path,
    check_speed_value,
    checked_items,
)
from .pairs import (  # noqa: F401 - StereoSettings and stereo_settings are used as api.<name>
    MAX_UPSCALE,
    StereoSettings,
    _pair_images,
    _params_risk_data,
    _settings_problem,
    orb_fields,
    stereo_settings,
)
from .registry import _load_model
from .stereo import LoadedStereo, check_stereo_size

MAX_THW_THRESHOLD_S = 10.0  # a larger THW threshold calls almost every frame critical
UNKNOWN = "unknown"  # the verdict of a pair that failed the stereo pair check


@dataclass
class LoadedRisk:
    """A :class:`~traffictwin.risk.model_io.RiskModel` (or corridor rule / hybrid), a
    description of where it came from and, for a model that reads the learned stereo network's
    disparity, that network (``stereo``)."""

    model: Any
    description: str
    stereo: LoadedStereo | None = None

    @property
    def disparity_key(self) -> str:
        """The disparity the model reads (``disp_sgm`` or ``disp_learned``)."""
        return _disparity_input(self.model)

    @property
    def meta(self) -> dict[str, Any]:
        return self.model.meta

    @property
    def domain(self) -> dict[str, Any]:
        d = self.model.meta.get("domain")
        return d if isinstance(d, dict) else {}

    @property
    def predictor(self) -> str:
        """What predicts: ``dave2`` (the network), ``hybrid`` (MLP on the corridor profile) or
        ``geometric`` (the corridor rule), and for the shipped model which candidate the
        validation chose (``hybrid (shipped: hybrid_s1, validation ROC-AUC 0.945)``)."""
        from traffictwin.risk.predictors import predictor_kind

        kind = predictor_kind(self.model)
        sh = self.model.meta.get("shipped")
        if isinstance(sh, dict) and sh.get("predictor"):
            if sh.get("note"):  # not chosen on validation: say why
                return f"{kind} (shipped: {sh['predictor']}, {sh['note']})"
            return f"{kind} (shipped: {sh['predictor']}, validation ROC-AUC {float(sh.get('roc_auc', float('nan'))):.3f})"
        return kind


def answered_by(risk: LoadedRisk, settings: StereoSettings) -> dict[str, Any]:
    """What answers a pair, as fields of ``traffictwin risk``'s JSON (and the serving app's
    ``/risk``): ``model`` (where it came from), ``predictor`` (:attr:`LoadedRisk.predictor`),
    ``stereo_settings`` (where the SGM / ORB settings came from) and, for a model that reads
    the learned stereo network's disparity, ``stereo_model``."""
    check_instance(risk, LoadedRisk, "risk", "a LoadedRisk (api.load_risk)")
    check_instance(settings, StereoSettings, "settings", "api.StereoSettings")
    out: dict[str, Any] = {
        "model": risk.description,
        "predictor": risk.predictor,
        "stereo_settings": settings.source,
    }
    if risk.stereo is not None:
        out["stereo_model"] = risk.stereo.description
    return out


def check_risk_domain(domain: Any, who: str) -> None:
    """Validate a risk model's ``domain`` metadata before it is used: ``speed_range`` two finite
    numbers lo < hi (m/s), ``max_speed`` a finite number > 0 (m/s), ``camera`` positive integer
    ``width`` / ``height`` (px), ``sgm`` / ``orb`` keyword settings of the SGM matcher and the
    ORB check. :class:`ModelDomainError` naming ``who`` and the key."""
    from traffictwin.stereo.orb import check_pair
    from traffictwin.stereo.sgm import compute_disparity

    if domain is None:
        return
    if not isinstance(domain, dict):
        raise ModelDomainError(f"{who}: 'domain' must be a mapping, got {type(domain).__name__}")

    def num(v: Any) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)

    rng = domain.get("speed_range")
    if rng is not None and not (
        isinstance(rng, (list, tuple)) and len(rng) == 2 and all(map(num, rng)) and rng[0] < rng[1]
    ):
        raise ModelDomainError(
            f"{who}: 'domain.speed_range' must be [lo, hi] m/s with lo < hi, got {rng!r}"
        )
    ms = domain.get("max_speed")
    if ms is not None and not (num(ms) and ms > 0):
        raise ModelDomainError(f"{who}: 'domain.max_speed' must be a number > 0 m/s, got {ms!r}")
    cam = domain.get("camera")
    if cam is not None:
        if not isinstance(cam, dict):
            raise ModelDomainError(
                f"{who}: 'domain.camera' must be a mapping (width, height px), got {cam!r}"
            )
        for k in ("width", "height"):
            v = cam.get(k)
            if v is not None and not (isinstance(v, int) and not isinstance(v, bool) and v > 0):
                raise ModelDomainError(
                    f"{who}: 'domain.camera.{k}' must be a positive integer (px), got {v!r}"
                )
    for key, func in (("sgm", compute_disparity), ("orb", check_pair)):
        if domain.get(key) is not None:
            why = _settings_problem(domain[key], func, ("left_bgr", "right_bgr", "matcher"))
            if why:
                raise ModelDomainError(f"{who}: 'domain.{key}': {why}")


def _disparity_input(model: Any) -> str:
    """The disparity key a risk model reads (its ``cfg.inputs``; ``disp_sgm`` when none)."""
    inputs = tuple(getattr(getattr(model, "cfg", None), "inputs", ()) or ())
    return next((k for k in inputs if k.startswith("disp_")), "disp_sgm")


def load_risk(
    model: str | os.PathLike,
    *,
    tracking_uri: str | None = None,
    stereo_model: str | os.PathLike | None = None,
) -> LoadedRisk:
    """Load a risk model by registry reference (``name@alias``; a bare alias means
    ``traffictwin-risk``) or model folder. A model that reads the learned stereo network's
    disparity (``disp_learned``) gets that network: ``stereo_model`` (its folder), else the
    folder :data:`PACKAGED_STEREO` inside the risk model's folder. Raises :class:`ApiError`."""
    from traffictwin.mlops.registry import RISK_NAME
    from traffictwin.risk.model_io import RiskModelError, load_risk_model

    from .stereo import SOURCE_KEYS, load_stereo

    check_path(model, "model", "a registry reference name@alias or a model folder path")
    check_optional_text(tracking_uri, "tracking_uri")
    if stereo_model is not None:
        check_path(stereo_model, "stereo_model", "a learned stereo model folder or reference")
    rm, desc = _load_model(
        model, load_risk_model, RiskModelError, "risk model", RISK_NAME, tracking_uri
    )
    check_risk_domain((rm.meta or {}).get("domain"), desc)
    key = _disparity_input(rm)
    if key != SOURCE_KEYS["learned"]:
        if stereo_model is not None:
            raise InputValueError(
                f"stereo_model: {desc} reads the disparity {key!r}, not the learned stereo "
                "network's ('disp_learned'); give no stereo model"
            )
        return LoadedRisk(rm, desc)
    folder = Path(model) if Path(model).is_dir() else None
    packaged = folder / PACKAGED_STEREO if folder is not None else None
    if stereo_model is None and packaged is not None and packaged.is_dir():
        stereo_model = packaged
    if stereo_model is None:
        raise ModelDomainError(
            f"{desc}: reads the learned stereo network's disparity ('disp_learned'); give that "
            "network's folder (stereo_model=..., --stereo-model models/stereo/learned)"
        )
    stereo = load_stereo(stereo_model, tracking_uri=tracking_uri)
    if stereo.net is None:
        raise InputValueError(
            f"stereo_model: {desc} reads the learned stereo network's disparity; 'sgm' is not it"
        )
    cam = ((rm.meta or {}).get("domain") or {}).get("camera") or {}
    if {"width", "height"} <= set(cam):
        check_stereo_size(stereo, int(cam["width"]), int(cam["height"]), desc)
    return LoadedRisk(rm, desc, stereo)


def speed_range(
    risk: LoadedRisk, params_path: str | os.PathLike | None = None
) -> tuple[float, float, str] | None:
    """``(lo, hi, source)`` in m/s of the speeds the model was trained on, or ``None`` if unknown
    (the order of sources: :mod:`traffictwin.api`, Training domain)."""
    check_instance(risk, LoadedRisk, "risk", "a LoadedRisk (api.load_risk)")
    d = risk.domain
    rng = d.get("speed_range")
    if isinstance(rng, (list, tuple)) and len(rng) == 2:
        return float(rng[0]), float(rng[1]), f"domain.speed_range of {risk.description}"
    if isinstance(d.get("max_speed"), (int, float)):
        return 0.0, float(d["max_speed"]), f"domain.max_speed of {risk.description}"
    if params_path is not None:
        rd = _params_risk_data(params_path)
        if isinstance(rd.get("max_speed"), (int, float)):
            return 0.0, float(rd["max_speed"]), f"risk_data.max_speed of {params_path}"
    return None


def _num(x: float) -> str:
    """``x`` short (``%g``) where that is exact, else with every digit (25.000001, not 25)."""
    short = f"{x:g}"
    return short if float(short) == x else repr(float(x))


def check_speed(
    risk: LoadedRisk, speed: float | None, params_path: str | os.PathLike | None = None
) -> list[str]:
    """Check ``speed`` (m/s) against the model: :class:`ApiError` when it is missing for a speed
    model, not finite, negative or outside the training range; returns warnings (a model
    without speed input; a speed model without a recorded range)."""
    cfg = risk.model.cfg
    notes: list[str] = []
    speed = check_speed_value(speed)
    if params_path is not None:
        _params_risk_data(params_path)  # a given params file is read and checked, never ignored
    if speed is None:
        if cfg.use_speed:
            raise InputValueError(
                f"speed: the model ({risk.description}) uses the subject speed; give it (m/s)"
            )
        return notes
    rng = speed_range(risk, params_path)
    if rng is not None and cfg.use_speed:
        lo, hi, src = rng
        if not lo <= speed <= hi:
            raise ModelDomainError(
                f"speed: {_num(speed)} m/s is outside the model's training range "
                f"[{_num(lo)}, {_num(hi)}] m/s ({src})"
            )
    if not cfg.use_speed:
        notes.append(
            f"speed: the model ({risk.description}) has no speed input; the speed only scales gap_m"
        )
    elif rng is None:
        notes.append(
            f"speed: the model ({risk.description}) records no training speed range; "
            "give a params file with risk_data.max_speed to check it"
        )
    return notes


def decision_cut(risk: LoadedRisk, thw_threshold: float) -> float | None:
    """The risk above which the model calls a frame critical at ``thw_threshold`` (s), as chosen
    on the validation split (``shipped.decision`` of a shipped predictor's metadata); ``None``
    when none was chosen for that threshold (the verdict then compares THW with the threshold)."""
    check_instance(risk, LoadedRisk, "risk", "a LoadedRisk (api.load_risk)")
    thw_threshold = check_thw_threshold(thw_threshold)
    dec = (risk.meta.get("shipped") or {}).get("decision") or {}
    for t, d in dec.items():
        try:
            if math.isclose(float(t), float(thw_threshold)) and isinstance(d, dict):
                return float(d["cut"])
        except (TypeError, ValueError, KeyError):
            continue
    return None


def risk_verdict(
    risk: float,
    speed: float | None,
    thw_threshold: float = PAPER["threshold_s"],
    cut: float | None = None,
    unreliable: str = "",
) -> dict[str, Any]:
    """THW from the normalised risk (``risk = min(1/THW, 20)/20`` ⇒ ``THW = 1/(20 risk)``; risk <= 0:
    no vehicle ahead, THW = inf) and the verdict ``critical`` iff THW < ``thw_threshold`` (s), or,
    with ``cut`` (the decision threshold chosen on validation, :func:`decision_cut`), iff
    ``risk > cut``. With ``speed`` (m/s) the implied free distance ``THW * speed`` (m) is added.

    ``unreliable``: why the stereo pair failed its check (:func:`traffictwin.stereo.orb.check_pair`'s
    ``reason``; "" = it passed). An unreliable pair has no verdict: ``verdict`` is ``"unknown"``,
    ``critical`` ``None`` and ``verdict_reason`` says why (risk and THW are what the model computed
    from images that cannot be trusted, never a verdict)."""
    if isinstance(risk, (bool, np.bool_)) or not isinstance(risk, (int, float, np.number)):
        raise InputValueError(f"risk: expected a number in [0, 1], got {risk!r}")
    speed = check_speed_value(speed)
    thw_threshold = check_thw_threshold(thw_threshold)
    if cut is not None and (
        isinstance(cut, (bool, np.bool_)) or not isinstance(cut, (int, float, np.number))
    ):
        raise InputValueError(f"cut: expected a risk in [0, 1] or None, got {cut!r}")
    if not isinstance(unreliable, str):
        raise InputValueError(f"unreliable: expected a string, got {type(unreliable).__name__}")
    thw = float(risk_to_thw(np.asarray(risk), cap=math.inf))
    crit = bool(risk > cut) if cut is not None else bool(thw < thw_threshold)
    out: dict[str, Any] = {
        "risk": risk,
        "thw_s": thw,
        "thw_threshold_s": thw_threshold,
        "critical": crit,
        "verdict": "critical" if crit else "uncritical",
        "verdict_reason": "",
    }
    if unreliable:
        out.update(
            critical=None,
            verdict=UNKNOWN,
            verdict_reason=f"the stereo pair failed its check ({unreliable})",
        )
    if cut is not None:
        out["decision_cut"] = cut
    if speed is not None:
        out["speed_m_s"] = float(speed)
        out["gap_m"] = thw * speed if math.isfinite(thw) else math.inf
    return out


def _frame_images(fr: Frame, risk: LoadedRisk, resize: bool) -> tuple[np.ndarray, np.ndarray]:
    """The BGR images of ``fr``, checked against the risk model's camera (:func:`_pair_images`)."""
    cam = risk.domain.get("camera")
    return _pair_images(fr, cam if isinstance(cam, dict) else None, risk.description, resize)


def check_thw_threshold(thw_threshold: Any, who: str = "thw_threshold") -> float:
    """A THW threshold (s): a finite number in (0, :data:`MAX_THW_THRESHOLD_S`] (not a bool)."""
    if isinstance(thw_threshold, (bool, np.bool_)) or not isinstance(
        thw_threshold, (int, float, np.integer, np.floating)
    ):
        raise InputValueError(f"{who}: expected a number of seconds, got {thw_threshold!r}")
    t = float(thw_threshold)
    if not (math.isfinite(t) and 0 < t <= MAX_THW_THRESHOLD_S):
        raise InputValueError(
            f"{who}: must be a time headway in (0, {MAX_THW_THRESHOLD_S:g}] s, got {thw_threshold}"
        )
    return t


def assess_risk(
    risk: LoadedRisk,
    frames: Iterable[Frame],
    *,
    speed: float | None = None,
    settings: StereoSettings | None = None,
    params_path: str | os.PathLike | None = None,
    resize: bool = False,
    batch_size: int = 16,
    thw_threshold: float = PAPER["threshold_s"],
) -> Iterator[dict[str, Any]]:
    """Stream risk rows for ``frames``: ORB pair check, SGM disparity and the network's risk,
    ``batch_size`` frames at a time (images are read when their batch comes, so memory is
    bounded by one batch, not by the number of frames). One dict per frame (``id``, ORB
    statistics, disparity summary, ``risk`` in [0, 1], THW verdict, per-frame timings).

    A pair that fails the ORB check (``orb_verdict`` "unreliable pair", ``orb_reason``: uniform
    images, no disparity, a vertical offset, swapped cameras) gets ``verdict`` "unknown",
    ``critical`` None and the reason in ``verdict_reason`` (:func:`risk_verdict`), never
    "uncritical" or "critical".

    The arguments are checked at the call (:class:`InputValueError` naming the argument); the
    frames when their batch comes. ``speed`` (m/s) is checked by :func:`check_speed` (its
    warnings are issued as :class:`ApiWarning`); ``settings`` default to :func:`stereo_settings`
    of the model's domain and ``params_path``.
    """
    check_instance(risk, LoadedRisk, "risk", "a LoadedRisk (api.load_risk)")
    items = checked_items(frames, Frame, "frames", "api.Frame(id, left, right)")
    batch_size = check_count(batch_size, "batch_size")
    check_flag(resize, "resize")
    if settings is not None:
        check_instance(settings, StereoSettings, "settings", "api.StereoSettings or None")
    check_thw_threshold(thw_threshold)
    for note in check_speed(risk, speed, params_path):
        warnings.warn(note, ApiWarning, stacklevel=2)
    st = settings or stereo_settings(risk.domain, params_path, risk.description)
    cut = decision_cut(risk, thw_threshold)
    return _assess(
        risk, items, check_speed_value(speed), st, resize, batch_size, thw_threshold, cut
    )


def _assess(
    risk: LoadedRisk,
    frames: Iterable[Frame],
    speed: float | None,
    st: StereoSettings,
    resize: bool,
    batch_size: int,
    thw_threshold: float,
    cut: float | None,
) -> Iterator[dict[str, Any]]:
    """The rows of :func:`assess_risk` (arguments checked)."""
    from traffictwin.stereo.orb import check_pair
    from traffictwin.stereo.sgm import compute_disparity

    from .stereo import disparities

    key = risk.disparity_key
    for chunk in _chunks(frames, batch_size):
        lefts, rights, disps, rows, reasons = [], [], [], [], []
        for fr in chunk:
            left, right = _frame_images(fr, risk, resize)
            t0 = time.perf_counter()
            orb = check_pair(left, right, **st.orb)
            t1 = time.perf_counter()
            disp = compute_disparity(left, right, **st.sgm)
            t2 = time.perf_counter()
            lefts.append(left)
            rights.append(right)
            disps.append(disp)
            reasons.append(orb.reason if orb.outlier else "")
            rows.append(
                {
                    "id": fr.id,
                    **orb_fields(orb),
                    "disp_valid_fraction": math.nan,  # of the disparity the model reads, below
                    "disp_median_px": math.nan,
                    "orb_ms": round((t1 - t0) * 1e3, 2),
                    "sgm_ms": round((t2 - t1) * 1e3, 2),
                }
            )
        left_n = np.stack(lefts)
        disp, _, net_ms = disparities(risk.stereo, left_n, np.stack(rights), np.stack(disps))
        for row, d in zip(rows, disp[key]):
            valid = d >= 0
            row["disp_valid_fraction"] = float(valid.mean())
            row["disp_median_px"] = float(np.median(d[valid])) if valid.any() else math.nan
            if risk.stereo is not None:
                row.update(disp_source=key, stereo_net_ms=round(net_ms, 2))
        t0 = time.perf_counter()
        sp = None if speed is None else np.full(len(chunk), speed, np.float32)
        pred = risk.model.predict(left_bgr=left_n, speed=sp, batch_size=batch_size, disparity=disp)
        ms = (time.perf_counter() - t0) * 1e3 / len(chunk)
        bad = [row["id"] for row, r in zip(rows, pred) if not np.isfinite(r)]
        if bad:
            raise ApiError(
                f"the model ({risk.description}) predicted a non-finite risk for frame {bad[0]!r}"
            )
        pred = np.clip(pred, 0.0, 1.0)  # the metric's range, always
        for row, r, why in zip(rows, pred, reasons):
            row.update(
                risk_verdict(float(r), speed, thw_threshold, cut, why), model_ms=round(ms, 2)
            )
            yield row
