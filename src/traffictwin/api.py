"""Public Python API: load a trained model, fuse grid maps, assess stereo risk.

The ``traffictwin`` command is a thin layer over these functions::

    from traffictwin import api

    fusion = api.load_fusion("traffictwin-fusion@champion")          # registry (name@alias)
    fusion = api.load_fusion("models/fusion/network")                # or a model folder
    for res in api.fuse(fusion, pairs, batch_size=8):                # batched inference
        res.masses, res.u                                           # (2, H, W), (H, W) float32

    risk = api.load_risk("traffictwin-risk@champion", tracking_uri="http://mlflow:5000")
    for row in api.assess_risk(risk, api.frames_in_folder("frames/"), speed=12.0):
        row["risk"], row["thw_s"]                                   # streamed in batches

Models
    A model reference is a registry ``name@alias`` (``champion`` / ``challenger``; a bare alias
    means ``traffictwin-risk@alias`` for risk and ``traffictwin-fusion@alias`` for fusion: one
    network serves every pose-noise level), or the path of a model folder (``model.ckpt`` +
    ``model_meta.json``, as the ``train_*`` stages write them). Registered models are loaded only through
    :func:`traffictwin.mlops.registry.load_registered`: every file checked against the SHA-256
    sealed at registration, checkpoints read with ``weights_only=True``; nothing is unpickled.

Registry
    ``tracking_uri`` (the CLI's ``--tracking-uri``), else ``MLFLOW_TRACKING_URI``, else the
    project's ``mlflow.db`` when run inside the project. A SQLite database that does not exist
    is an error, never created (no stray ``mlflow.db``); outside the project without a URI the
    error says how to name one. :func:`connect` probes the registry once, so a dead server is
    one line ("unreachable"), not "no model registered"; the CLI bounds MLflow's HTTP retries
    and timeout (:data:`HTTP_ENV`) so that takes seconds, not minutes.

Training domain (issue 18, defect 7): inputs outside what the model was trained on are refused
    with the reason. Fusion: the grid's rows, columns and cell size must equal the model's
    training grid (``grid`` of its metadata). Risk: images must have the training camera's size
    (``domain.camera``) unless ``resize=True``, which resizes both images to it *before* ORB and
    SGM, so the disparity comes out in the camera's pixel scale (disparity in px scales with
    image width). Speed: checked against ``domain.speed_range`` ([lo, hi] m/s) or
    ``domain.max_speed`` (m/s) of the model's metadata, else ``risk_data.max_speed`` of the
    params file passed as ``params_path``; models trained before these keys existed have no
    range: the speed is then only checked to be finite and >= 0 (a warning says so). A model
    without a speed input warns that ``speed`` only scales ``gap_m``. The predicted risk is
    clamped to [0, 1].

THW
    Rows carry ``thw_s`` (s) and ``gap_m`` (m) as Python floats, ``inf`` when nothing is ahead
    (risk 0). The CLI writes them as ``null`` in JSON and as an empty field in CSV (one rule for
    every non-finite value), never as ``inf``.

This module imports only NumPy at import time; torch, OpenCV and MLflow are imported by the
functions that need them (``traffictwin --help`` stays fast).
"""

from __future__ import annotations

import math
import os
import time
import warnings
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from traffictwin.risk.metric import CRITICAL_THW, risk_to_thw

__all__ = [
    "ALIASES",
    "ApiError",
    "ApiWarning",
    "Frame",
    "FusePair",
    "FuseResult",
    "FusionModel",
    "LoadedRisk",
    "assess_risk",
    "connect",
    "frames_in_folder",
    "fuse",
    "load_fusion",
    "load_masses",
    "load_risk",
    "read_image",
    "resolve_tracking_uri",
]

ALIASES = ("champion", "challenger")
SIMPLEX_TOL = 1e-4
DIVISOR = 16  # the fusion network's output stride: grid rows and cols must be multiples
IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm")
#: MLflow HTTP client settings for interactive use: no retries, 5 s per request (MLflow's own
#: defaults retry for minutes against a dead server). The CLI sets them unless already set.
HTTP_ENV = {
    "MLFLOW_HTTP_REQUEST_MAX_RETRIES": "0",
    "MLFLOW_HTTP_REQUEST_TIMEOUT": "5",
    "MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR": "0",
}


class ApiError(ValueError):
    """A user-facing error in one line naming the file / argument / model and what was expected."""


class ApiWarning(UserWarning):
    """An input the model does not use or cannot check (one line; the CLI prints it to stderr)."""


# ============================================================================ registry


def resolve_tracking_uri(tracking_uri: str | None = None) -> str:
    """The registry URI to use (see the module doc); never creates a database.

    Raises :class:`ApiError` when no URI is given outside the project, or when a SQLite
    database (or a local file store) does not exist.
    """
    from traffictwin.mlops.tracking import ENV_URI, repo_root, sqlite_path

    uri = tracking_uri or os.environ.get(ENV_URI)
    if not uri:
        root = repo_root()
        if not (root / "dvc.yaml").is_file():
            raise ApiError(
                "no model registry: pass --tracking-uri URI (or set MLFLOW_TRACKING_URI), run "
                f"inside the traffictwin project (its mlflow.db), or pass --model PATH of a model "
                f"folder ({Path.cwd()} is not in the project)"
            )
        uri = f"sqlite:///{root / 'mlflow.db'}"
    db = sqlite_path(uri)
    if db is not None and not db.is_file():
        raise ApiError(
            f"{uri}: no MLflow database at {db} (not creating one): run the pipeline and "
            "`python -m pipelines.promote` first, or pass --tracking-uri"
        )
    if uri.startswith(("file:", "/", "./", "../")):  # a local file store
        folder = Path(uri[len("file://") :] if uri.startswith("file://") else uri)
        if not folder.is_dir():
            raise ApiError(f"{uri}: no MLflow file store at {folder} (not creating one)")
    return uri


def _first_line(exc: BaseException, limit: int = 200) -> str:
    text = str(exc).strip().splitlines()
    msg = text[0] if text else ""
    return (msg[:limit] + "…") if len(msg) > limit else msg


def connect(tracking_uri: str | None = None):
    """An ``MlflowClient`` on :func:`resolve_tracking_uri` after one probe of the registry.

    Raises :class:`ApiError` ("unreachable") when the probe fails (dead server, wrong URI,
    unreadable database), so a missing model is never confused with a missing registry.
    """
    from traffictwin.mlops import registry as reg

    uri = resolve_tracking_uri(tracking_uri)
    try:
        cl = reg.client(uri)
        cl.search_registered_models(max_results=1)
    except Exception as exc:  # noqa: BLE001 - any failure of the probe means "unreachable"
        raise ApiError(
            f"{uri}: model registry unreachable ({type(exc).__name__}: {_first_line(exc)})"
        ) from None
    return cl


def _split_ref(model: str | os.PathLike) -> tuple[str | None, str | None, Path | None]:
    """``(name or None, alias, None)`` for a registry reference, ``(None, None, path)`` for a folder."""
    text = str(model)
    if text in ALIASES:
        return None, text, None
    p = Path(text)
    if p.exists():
        return None, None, p
    if "@" in text and "/" not in text:
        name, alias = text.rsplit("@", 1)
        if name and alias:
            return name, alias, None
    raise ApiError(
        f"--model: '{text}' is neither a registry reference (name@alias, or {' / '.join(ALIASES)}) "
        "nor an existing model folder"
    )


def _load_registered(cl, name: str, alias: str, loader, what: str):
    from traffictwin.mlops import registry as reg

    try:
        mv = reg.require_alias(cl, name, alias)
    except reg.RegistryError as exc:
        raise ApiError(str(exc)) from None
    uri = reg.version_uri(name, mv.version)
    try:
        return reg.load_registered(uri, loader, cl=cl), f"{name}@{alias} ({uri})"
    except reg.GateError as exc:  # tampered, legacy pickle, missing files, ...
        raise ApiError(_first_line(exc, 400)) from None
    except Exception as exc:  # noqa: BLE001
        raise ApiError(
            f"{uri}: cannot load the registered {what} ({type(exc).__name__}: {_first_line(exc)})"
        ) from None


# ============================================================================ fusion


@dataclass
class FusionModel:
    """A fusion network (eval mode, CPU), its metadata, training grid and a description."""

    net: Any
    meta: dict[str, Any]
    grid: dict[str, float]
    description: str


def load_fusion(model: str | os.PathLike, *, tracking_uri: str | None = None) -> FusionModel:
    """Load the fusion network by registry reference (``name@alias``, or a bare alias of
    ``traffictwin-fusion``: one network serves every pose-noise level) or model folder. Raises
    :class:`ApiError`."""
    from traffictwin.fusion.model_io import FusionModelError, load_fusion_model
    from traffictwin.mlops.registry import FUSION_NAME

    name, alias, path = _split_ref(model)
    if path is None:
        cl = connect(tracking_uri)
        net, desc = _load_registered(
            cl, name or FUSION_NAME, alias, load_fusion_model, "fusion model"
        )
    else:
        try:
            net = load_fusion_model(path)
        except FusionModelError as exc:
            raise ApiError(str(exc)) from None
        desc = str(path)
    meta = dict(getattr(net, "meta", {}) or {})
    return FusionModel(net, meta, dict(meta.get("grid") or {}), desc)


def load_masses(path: str | os.PathLike) -> tuple[np.ndarray, float | None, np.ndarray | None]:
    """Read and validate an evidential grid ``.npz``: masses ``(2, H, W)`` float32, the optional
    ``cell`` (m) and the optional sensor ``pose`` (x m, y m, yaw rad). Raises :class:`ApiError`."""
    from traffictwin.evidential.masses import check_masses, clean_masses

    path = Path(path)
    if not path.is_file():
        raise ApiError(f"{path}: file not found")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as exc:  # noqa: BLE001 - zip/format errors of all kinds
        raise ApiError(f"{path}: not a readable .npz file ({type(exc).__name__}: {exc})") from None
    missing = [k for k in ("m_free", "m_occ") if k not in data]
    if missing:
        raise ApiError(
            f"{path}: array(s) {missing} missing (has {sorted(data)}); expected m_free and m_occ, (H, W) float"
        )
    mf, mo = data["m_free"], data["m_occ"]
    for k, a in (("m_free", mf), ("m_occ", mo)):
        if a.ndim != 2:
            raise ApiError(f"{path}: '{k}' must be a 2-D (H, W) grid, got shape {a.shape}")
        if not np.issubdtype(a.dtype, np.floating):
            raise ApiError(f"{path}: '{k}' must be a float array of masses, got dtype {a.dtype}")
    if mf.shape != mo.shape:
        raise ApiError(f"{path}: 'm_free' {mf.shape} and 'm_occ' {mo.shape} differ in shape")
    m = np.stack([mf, mo]).astype(np.float64)
    try:
        m = check_masses(m, f"{path}: masses (m_free, m_occ)", tol=SIMPLEX_TOL)
    except ValueError as exc:
        raise ApiError(str(exc)) from None
    m = clean_masses(m).astype(np.float32)
    cell = None
    if "cell" in data:
        c = np.asarray(data["cell"])
        if (
            c.size != 1
            or not np.issubdtype(c.dtype, np.number)
            or not (float(c) > 0 and math.isfinite(float(c)))
        ):
            raise ApiError(f"{path}: 'cell' must be one positive number (m per cell), got {c!r}")
        cell = float(c)
    pose = None
    if "pose" in data:
        pz = np.asarray(data["pose"])
        if pz.shape != (3,) or not np.issubdtype(pz.dtype, np.number) or not np.isfinite(pz).all():
            raise ApiError(f"{path}: 'pose' must be 3 finite numbers x, y, yaw (m, m, rad)")
        pose = pz.astype(np.float64)
    return m, cell, pose


@dataclass
class FusePair:
    """One fusion input: maps ``(2, H, W)`` in their sensor frames, world poses (x, y, yaw; m,
    m, rad), the cell size (m; ``None`` = the model's) and an id."""

    m1: np.ndarray
    m2: np.ndarray
    pose1: np.ndarray
    pose2: np.ndarray
    cell: float | None = None
    id: str = ""


@dataclass
class FuseResult:
    """Fused masses ``(2, H, W)`` and ``u (H, W)`` (float32, map 1's frame), map 2 prealigned,
    the relative pose used (3,), the cell (m) and the id of the pair."""

    id: str
    masses: np.ndarray
    u: np.ndarray
    m2_prealigned: np.ndarray
    rel_pose: np.ndarray
    cell: float
    m1: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))


def check_fusion_domain(
    model: FusionModel, shape: tuple[int, int], cell: float | None, who: str
) -> float:
    """The cell size to use for a grid of ``shape`` (rows, cols); :class:`ApiError` naming
    ``who`` unless the grid matches the model's training grid (rows, cols, cell)."""
    h, w = shape
    if h % DIVISOR or w % DIVISOR:
        raise ApiError(
            f"{who}: grid {h}x{w} cells: rows and cols must be divisible by {DIVISOR} (network output stride)"
        )
    g = model.grid
    if "rows" in g and "cols" in g and (int(g["rows"]), int(g["cols"])) != (h, w):
        raise ApiError(
            f"{who}: grid {h}x{w} cells (rows x cols) but the model ({model.description}) was "
            f"trained on {int(g['rows'])}x{int(g['cols'])}"
        )
    if cell is None:
        cell = float(g["cell"]) if "cell" in g else None
    if cell is None:
        raise ApiError(
            f"{who}: grid cell size unknown: pass --cell (m per cell) or store 'cell' in the .npz"
        )
    if "cell" in g and abs(float(g["cell"]) - cell) > 1e-9:
        raise ApiError(
            f"{who}: maps have {cell} m cells but the model ({model.description}) was trained on {g['cell']} m cells"
        )
    return float(cell)


def _chunks(items: Iterable[Any], n: int) -> Iterator[list[Any]]:
    buf: list[Any] = []
    for it in items:
        buf.append(it)
        if len(buf) == n:
            yield buf
            buf = []
    if buf:
        yield buf


def fuse(
    model: FusionModel, pairs: Iterable[FusePair], *, batch_size: int = 8
) -> Iterator[FuseResult]:
    """Prealign each pair's map 2 into map 1's frame by the poses and fuse with the network,
    ``batch_size`` pairs per forward pass. Pairs are consumed lazily and results yielded in
    order, so memory stays bounded by one batch. Raises :class:`ApiError` for a pair outside the
    training grid."""
    from traffictwin.fusion.model_io import predict_masses
    from traffictwin.fusion.pairs import prealign
    from traffictwin.grid import GridSpec

    if batch_size < 1:
        raise ApiError(f"batch_size must be >= 1, got {batch_size}")
    for chunk in _chunks(pairs, batch_size):
        xs, prep = [], []
        for p in chunk:
            if p.m1.shape != p.m2.shape or p.m1.ndim != 3 or p.m1.shape[0] != 2:
                raise ApiError(
                    f"pair {p.id!r}: maps must both be (2, H, W), got {p.m1.shape} and {p.m2.shape}"
                )
            cell = check_fusion_domain(model, p.m1.shape[1:], p.cell, f"pair {p.id!r}")
            grid = GridSpec(rows=p.m1.shape[1], cols=p.m1.shape[2], cell=cell)
            m2w, rel = prealign(p.m2, np.asarray(p.pose1, float), np.asarray(p.pose2, float), grid)
            xs.append(np.concatenate([p.m1, m2w]).astype(np.float32))
            prep.append((p, m2w, rel, cell))
        m, u = predict_masses(model.net, np.stack(xs), batch_size=batch_size)
        for k, (p, m2w, rel, cell) in enumerate(prep):
            yield FuseResult(p.id, m[k], u[k], m2w, rel, cell, p.m1)


# ============================================================================ risk


@dataclass
class LoadedRisk:
    """A :class:`~traffictwin.risk.model_io.RiskModel` and a description of where it came from."""

    model: Any
    description: str

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
            return f"{kind} (shipped: {sh['predictor']}, validation ROC-AUC {float(sh.get('roc_auc', float('nan'))):.3f})"
        return kind


def load_risk(model: str | os.PathLike, *, tracking_uri: str | None = None) -> LoadedRisk:
    """Load a risk network by registry reference (``name@alias``; a bare alias means
    ``traffictwin-risk``) or model folder. Raises :class:`ApiError`."""
    from traffictwin.mlops.registry import RISK_NAME
    from traffictwin.risk.model_io import RiskModelError, load_risk_model

    name, alias, path = _split_ref(model)
    if path is None:
        cl = connect(tracking_uri)
        rm, desc = _load_registered(cl, name or RISK_NAME, alias, load_risk_model, "risk model")
        return LoadedRisk(rm, desc)
    try:
        return LoadedRisk(load_risk_model(path), str(path))
    except RiskModelError as exc:
        raise ApiError(str(exc)) from None


def read_image(path: str | os.PathLike) -> np.ndarray:
    """An 8-bit BGR image (grayscale is expanded to 3 channels); errors name the file."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise ApiError(f"{path}: image not found")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ApiError(f"{path}: not a readable image (OpenCV could not decode it)")
    if img.dtype != np.uint8:
        raise ApiError(f"{path}: expected an 8-bit image, got {img.dtype}")
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    elif img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    elif img.shape[2] != 3:
        raise ApiError(
            f"{path}: expected a grayscale, BGR or BGRA image, got {img.shape[2]} channels"
        )
    return np.ascontiguousarray(img)


@dataclass
class Frame:
    """One stereo pair: an id and the left/right images as paths (read when their batch comes)
    or as BGR uint8 arrays."""

    id: str
    left: str | os.PathLike | np.ndarray
    right: str | os.PathLike | np.ndarray


def frames_in_folder(folder: str | os.PathLike) -> list[Frame]:
    """A :class:`Frame` for every ``<id>_left.<ext>`` / ``<id>_right.<ext>`` in ``folder``
    (sorted by id; nothing decoded). Errors on a folder without pairs and on an image without
    its partner."""
    folder = Path(folder)
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


@dataclass
class StereoSettings:
    """SGM / ORB keyword settings and where they came from."""

    sgm: dict[str, Any]
    orb: dict[str, Any]
    source: str


def _params_risk_data(params_path: str | os.PathLike) -> dict[str, Any]:
    import yaml

    path = Path(params_path)
    if not path.is_file():
        raise ApiError(f"--params: {path} not found")
    try:
        cfg = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ApiError(f"{path}: not valid YAML ({_first_line(exc)})") from None
    rd = cfg.get("risk_data") if isinstance(cfg, dict) else None
    return rd if isinstance(rd, dict) else {}


def stereo_settings(
    domain: Any, params_path: str | os.PathLike | None, model_desc: str = "the model"
) -> StereoSettings:
    """SGM/ORB settings the risk data were made with: ``domain.sgm`` / ``domain.orb`` of the
    model's metadata if present; else ``risk_data.sgm`` / ``risk_data.orb`` of the params file
    ``params_path``; else the library defaults."""
    if isinstance(domain, dict) and (
        isinstance(domain.get("sgm"), dict) or isinstance(domain.get("orb"), dict)
    ):
        return StereoSettings(
            dict(domain.get("sgm") or {}),
            dict(domain.get("orb") or {}),
            f"metadata of {model_desc}",
        )
    if params_path:
        rd = _params_risk_data(params_path)
        if isinstance(rd.get("sgm"), dict) or isinstance(rd.get("orb"), dict):
            return StereoSettings(
                dict(rd.get("sgm") or {}), dict(rd.get("orb") or {}), str(params_path)
            )
    return StereoSettings({}, {}, "library defaults")


def speed_range(
    risk: LoadedRisk, params_path: str | os.PathLike | None = None
) -> tuple[float, float, str] | None:
    """``(lo, hi, source)`` in m/s of the speeds the model was trained on, or ``None`` if unknown
    (see the module doc for the order of sources)."""
    d = risk.domain
    rng = d.get("speed_range")
    if isinstance(rng, (list, tuple)) and len(rng) == 2:
        return float(rng[0]), float(rng[1]), f"domain.speed_range of {risk.description}"
    if isinstance(d.get("max_speed"), (int, float)):
        return 0.0, float(d["max_speed"]), f"domain.max_speed of {risk.description}"
    if params_path:
        rd = _params_risk_data(params_path)
        if isinstance(rd.get("max_speed"), (int, float)):
            return 0.0, float(rd["max_speed"]), f"risk_data.max_speed of {params_path}"
    return None


def check_speed(
    risk: LoadedRisk, speed: float | None, params_path: str | os.PathLike | None = None
) -> list[str]:
    """Check ``speed`` (m/s) against the model: :class:`ApiError` when it is missing for a speed
    model, not finite, negative or outside the training range; returns warnings (a model
    without speed input; a speed model without a recorded range)."""
    cfg = risk.model.cfg
    notes: list[str] = []
    if speed is None:
        if cfg.use_speed:
            raise ApiError(
                f"the model ({risk.description}) uses the subject speed: pass --speed (m/s)"
            )
        return notes
    if not (math.isfinite(speed) and speed >= 0):
        raise ApiError(f"--speed: must be a finite speed >= 0 m/s, got {speed}")
    rng = speed_range(risk, params_path)
    if rng is not None and cfg.use_speed:
        lo, hi, src = rng
        if not lo <= speed <= hi:
            raise ApiError(
                f"--speed: {speed:g} m/s is outside the model's training range [{lo:g}, {hi:g}] m/s ({src})"
            )
    if not cfg.use_speed:
        notes.append(
            f"--speed: the model ({risk.description}) has no speed input; the speed only scales gap_m"
        )
    elif rng is None:
        notes.append(
            f"--speed: the model ({risk.description}) records no training speed range; "
            "pass --params with risk_data.max_speed to check it"
        )
    return notes


def decision_cut(risk: LoadedRisk, thw_threshold: float) -> float | None:
    """The risk above which the model calls a frame critical at ``thw_threshold`` (s), as chosen
    on the validation split (``shipped.decision`` of a shipped predictor's metadata); ``None``
    when none was chosen for that threshold (the verdict then compares THW with the threshold)."""
    dec = (risk.meta.get("shipped") or {}).get("decision") or {}
    for t, d in dec.items():
        try:
            if math.isclose(float(t), float(thw_threshold)) and isinstance(d, dict):
                return float(d["cut"])
        except (TypeError, ValueError, KeyError):
            continue
    return None


def risk_verdict(
    risk: float, speed: float | None, thw_threshold: float = CRITICAL_THW, cut: float | None = None
) -> dict[str, Any]:
    """THW from the normalised risk (``risk = min(1/THW, 20)/20`` ⇒ ``THW = 1/(20 risk)``; risk <= 0:
    no vehicle ahead, THW = inf) and the verdict ``critical`` iff THW < ``thw_threshold`` (s), or,
    with ``cut`` (the decision threshold chosen on validation, :func:`decision_cut`), iff
    ``risk > cut``. With ``speed`` (m/s) the implied free distance ``THW * speed`` (m) is added."""
    thw = float(risk_to_thw(np.asarray(risk), cap=math.inf))
    crit = bool(risk > cut) if cut is not None else bool(thw < thw_threshold)
    out: dict[str, Any] = {
        "risk": risk,
        "thw_s": thw,
        "thw_threshold_s": thw_threshold,
        "critical": crit,
        "verdict": "critical" if crit else "uncritical",
    }
    if cut is not None:
        out["decision_cut"] = cut
    if speed is not None:
        out["speed_m_s"] = float(speed)
        out["gap_m"] = thw * speed if math.isfinite(thw) else math.inf
    return out


def _frame_images(fr: Frame, risk: LoadedRisk, resize: bool) -> tuple[np.ndarray, np.ndarray]:
    import cv2

    left = fr.left if isinstance(fr.left, np.ndarray) else read_image(fr.left)
    right = fr.right if isinstance(fr.right, np.ndarray) else read_image(fr.right)
    ln, rn = (
        str(x) if not isinstance(x, np.ndarray) else f"frame {fr.id!r}" for x in (fr.left, fr.right)
    )
    if left.shape != right.shape:
        raise ApiError(
            f"{rn}: size {right.shape[1]}x{right.shape[0]} differs from {ln}'s "
            f"{left.shape[1]}x{left.shape[0]} (W x H)"
        )
    cam = risk.domain.get("camera")
    if isinstance(cam, dict) and "width" in cam and "height" in cam:
        cw, ch = int(cam["width"]), int(cam["height"])
        if (left.shape[1], left.shape[0]) != (cw, ch):
            if not resize:
                raise ApiError(
                    f"{ln}: image size {left.shape[1]}x{left.shape[0]} differs from the model's "
                    f"training camera {cw}x{ch} (W x H, domain.camera of {risk.description}); pass "
                    "--resize to resize both images to it (disparity then in the camera's pixel scale)"
                )
            left = cv2.resize(left, (cw, ch), interpolation=cv2.INTER_AREA)
            right = cv2.resize(right, (cw, ch), interpolation=cv2.INTER_AREA)
    return left, right


def assess_risk(
    risk: LoadedRisk,
    frames: Iterable[Frame],
    *,
    speed: float | None = None,
    settings: StereoSettings | None = None,
    params_path: str | os.PathLike | None = None,
    resize: bool = False,
    batch_size: int = 16,
    thw_threshold: float = CRITICAL_THW,
) -> Iterator[dict[str, Any]]:
    """Stream risk rows for ``frames``: ORB pair check, SGM disparity and the network's risk,
    ``batch_size`` frames at a time (images are read when their batch comes, so memory is
    bounded by one batch, not by the number of frames). One dict per frame (``id``, ORB
    statistics, disparity summary, ``risk`` in [0, 1], THW verdict, per-frame timings).

    ``speed`` (m/s) is checked by :func:`check_speed` (its warnings are issued as
    :class:`ApiWarning`); ``settings`` default to :func:`stereo_settings` of the model's domain and
    ``params_path``.
    """
    from traffictwin.stereo.orb import check_pair
    from traffictwin.stereo.sgm import compute_disparity

    if batch_size < 1:
        raise ApiError(f"batch_size must be >= 1, got {batch_size}")
    if not thw_threshold > 0:
        raise ApiError(f"--thw-threshold: must be > 0 s, got {thw_threshold}")
    for note in check_speed(risk, speed, params_path):
        warnings.warn(note, ApiWarning, stacklevel=2)
    st = settings or stereo_settings(risk.domain, params_path, risk.description)
    cut = decision_cut(risk, thw_threshold)
    for chunk in _chunks(frames, batch_size):
        lefts, disps, rows = [], [], []
        for fr in chunk:
            left, right = _frame_images(fr, risk, resize)
            t0 = time.perf_counter()
            orb = check_pair(left, right, **st.orb)
            t1 = time.perf_counter()
            disp = compute_disparity(left, right, **st.sgm)
            t2 = time.perf_counter()
            valid = disp >= 0
            lefts.append(left)
            disps.append(disp)
            rows.append(
                {
                    "id": fr.id,
                    "orb_outlier": bool(orb.outlier),
                    "orb_verdict": "unreliable pair" if orb.outlier else "ok",
                    "orb_n_matches": int(orb.n_matches),
                    "orb_n_reliable": int(orb.n_reliable),
                    "orb_mean_dx": float(orb.mean_dx),
                    "orb_mean_dy": float(orb.mean_dy),
                    "disp_valid_fraction": float(valid.mean()),
                    "disp_median_px": float(np.median(disp[valid])) if valid.any() else math.nan,
                    "orb_ms": round((t1 - t0) * 1e3, 2),
                    "sgm_ms": round((t2 - t1) * 1e3, 2),
                }
            )
        t0 = time.perf_counter()
        sp = None if speed is None else np.full(len(chunk), speed, np.float32)
        pred = risk.model.predict(
            left_bgr=np.stack(lefts), disp_sgm=np.stack(disps), speed=sp, batch_size=batch_size
        )
        ms = (time.perf_counter() - t0) * 1e3 / len(chunk)
        bad = [row["id"] for row, r in zip(rows, pred) if not np.isfinite(r)]
        if bad:
            raise ApiError(
                f"the model ({risk.description}) predicted a non-finite risk for frame {bad[0]!r}"
            )
        pred = np.clip(pred, 0.0, 1.0)  # the metric's range, always
        for row, r in zip(rows, pred):
            row.update(risk_verdict(float(r), speed, thw_threshold, cut), model_ms=round(ms, 2))
            yield row
