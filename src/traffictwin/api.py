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
    "InputFileError",
    "InputValueError",
    "ModelDomainError",
    "Frame",
    "FusePair",
    "FuseResult",
    "FusionModel",
    "LoadedRisk",
    "assess_risk",
    "check_cell",
    "check_mass_grids",
    "check_pose",
    "check_speed_value",
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
    # no "Downloading artifacts" bar before a load's one-line result or error (issue 35, defect 20)
    "MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR": "false",
}


class ApiError(ValueError):
    """A user-facing error in one line naming the file / argument / model and what was expected."""


class InputFileError(ApiError):
    """An input file or folder is missing, unreadable or not of the expected format."""


class InputValueError(ApiError):
    """An argument's value (masses, pose, cell, speed, image array, threshold) is invalid."""


class ModelDomainError(ApiError):
    """An input outside what the model was trained on (grid, cell, camera, speed)."""


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


def _load_registered(cl, name: str, alias: str, loader, what: str, family: str | None = None):
    """Load ``name@alias`` with ``loader``. ``family``: the registry name of this problem
    (``traffictwin-fusion``...): a name outside it is refused before anything is downloaded,
    and the hint of a missing alias lists only the registered models this loader can load."""
    from traffictwin.mlops import registry as reg

    def loadable(n: str) -> bool:
        return family is None or n == family or n.startswith(f"{family}-")

    if not loadable(name):
        raise ApiError(
            f"--model: '{name}@{alias}' is not a {what}; {what}s are registered as '{family}'"
        )
    mv = reg.get_alias(cl, name, alias)
    if mv is None:
        known = [n for n in reg._registered_names(cl) if loadable(n)]
        hint = (
            f"registered {what}s: {', '.join(known)}"
            if known
            else f"no {what} is registered yet (run the promotion gate: `make promote`)"
        )
        raise ApiError(f"model '{name}' has no version with alias '{alias}' ({hint})")
    uri = reg.version_uri(name, mv.version)
    try:
        return reg.load_registered(uri, loader, cl=cl, cache=True), f"{name}@{alias} ({uri})"
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
            cl, name or FUSION_NAME, alias, load_fusion_model, "fusion model", FUSION_NAME
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
    from traffictwin.io.limits import InputError, check_grid_cells, npz_headers

    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{path}: file not found")
    keys = ("m_free", "m_occ", "cell", "pose")  # the arrays read; no other one is decompressed
    try:  # zip and sizes from the .npy headers, before any array is decompressed
        heads = npz_headers(path, keys)
    except InputError as exc:
        raise InputFileError(f"{exc}; expected arrays m_free and m_occ, (H, W) float") from None
    try:
        for k in heads:
            check_grid_cells(heads[k].shape, f"{path}: array '{k}'")
    except InputError as exc:
        raise InputValueError(str(exc)) from None
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in heads}
            names = sorted(z.files)
    except Exception as exc:  # noqa: BLE001 - zip/format errors of all kinds
        raise InputFileError(
            f"{path}: not a readable .npz file ({type(exc).__name__}: {exc})"
        ) from None
    missing = [k for k in ("m_free", "m_occ") if k not in data]
    if missing:
        raise InputFileError(
            f"{path}: array(s) {missing} missing (has {names}); expected m_free and m_occ, (H, W) float"
        )
    mf, mo = data["m_free"], data["m_occ"]
    for k, a in (("m_free", mf), ("m_occ", mo)):
        if a.ndim != 2:
            raise InputValueError(f"{path}: '{k}' must be a 2-D (H, W) grid, got shape {a.shape}")
        if not np.issubdtype(a.dtype, np.floating):
            raise InputValueError(
                f"{path}: '{k}' must be a float array of masses, got dtype {a.dtype}"
            )
    if mf.shape != mo.shape:
        raise InputValueError(f"{path}: 'm_free' {mf.shape} and 'm_occ' {mo.shape} differ in shape")
    m = check_mass_grids(np.stack([mf, mo]), str(path))  # the one validator of the API
    cell = check_cell(data["cell"], str(path)) if "cell" in data else None
    pose = check_pose(data["pose"], f"{path}: 'pose'") if "pose" in data else None
    return m, cell, pose


def _is_real(a: np.ndarray) -> bool:
    return np.issubdtype(a.dtype, np.floating) or (
        np.issubdtype(a.dtype, np.integer) and a.dtype != np.bool_
    )


def check_pose(value: Any, who: str) -> np.ndarray:
    """A world pose as float64 ``(3,)`` = x (m), y (m), yaw (rad): three finite real numbers
    (a complex pose is refused, never cast); :class:`InputValueError` naming ``who``."""
    try:
        a = np.asarray(value)
    except Exception:  # noqa: BLE001 - ragged lists and other non-arrays
        a = np.asarray(None)
    if a.shape != (3,) or not _is_real(a) or not np.isfinite(a).all():
        got = f"shape {a.shape}, dtype {a.dtype}" if a.dtype != object else type(value).__name__
        raise InputValueError(
            f"{who}: expected 3 finite real numbers x, y, yaw (m, m, rad), got {got}"
        )
    return a.astype(np.float64)


def check_cell(value: Any, who: str) -> float | None:
    """A cell size (m): ``None`` or one finite positive real number; :class:`InputValueError`."""
    if value is None:
        return None
    a = np.asarray(value)
    if a.size != 1 or not _is_real(a) or not (math.isfinite(float(a)) and float(a) > 0):
        raise InputValueError(
            f"{who}: 'cell' must be one positive real number (m per cell), got {value!r}"
        )
    return float(a)


def check_mass_grids(m: Any, who: str) -> np.ndarray:
    """Masses ``(2, H, W)`` (free, occupied) of a real float dtype, finite, on the simplex
    within :data:`SIMPLEX_TOL` (then cleaned onto it); float32. :class:`InputValueError`."""
    from traffictwin.evidential.masses import check_masses, clean_masses

    a = np.asarray(m)
    if a.ndim != 3 or a.shape[0] != 2:
        raise InputValueError(f"{who}: masses must be (2, H, W) (free, occupied), got {a.shape}")
    if not np.issubdtype(a.dtype, np.floating):
        raise InputValueError(f"{who}: masses must be a real float array, got dtype {a.dtype}")
    try:
        checked = check_masses(a.astype(np.float64), f"{who}: masses (free, occupied)", SIMPLEX_TOL)
    except ValueError as exc:
        raise InputValueError(str(exc)) from None
    return clean_masses(checked).astype(np.float32)


def check_speed_value(speed: Any, who: str = "speed") -> float | None:
    """``None`` or one finite real speed >= 0 (m/s); :class:`InputValueError` naming ``who``."""
    if speed is None:
        return None
    if isinstance(speed, (bool, np.bool_)) or not isinstance(speed, (int, float, np.number)):
        raise InputValueError(f"{who}: expected a number of m/s, got {type(speed).__name__}")
    if not (math.isfinite(float(speed)) and float(speed) >= 0):
        raise InputValueError(f"{who}: must be a finite speed >= 0 m/s, got {speed}")
    return float(speed)


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
        raise ModelDomainError(
            f"{who}: grid {h}x{w} cells: rows and cols must be divisible by {DIVISOR} (network output stride)"
        )
    g = model.grid
    if "rows" in g and "cols" in g and (int(g["rows"]), int(g["cols"])) != (h, w):
        raise ModelDomainError(
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
        raise ModelDomainError(
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
            who = f"pair {p.id!r}"
            m1, m2 = check_mass_grids(p.m1, f"{who} m1"), check_mass_grids(p.m2, f"{who} m2")
            if m1.shape != m2.shape:
                raise InputValueError(
                    f"{who}: maps must both be (2, H, W) of one size, got {m1.shape} and {m2.shape}"
                )
            pose1, pose2 = check_pose(p.pose1, f"{who} pose1"), check_pose(p.pose2, f"{who} pose2")
            cell = check_fusion_domain(model, m1.shape[1:], check_cell(p.cell, who), who)
            grid = GridSpec(rows=m1.shape[1], cols=m1.shape[2], cell=cell)
            m2w, rel = prealign(m2, pose1, pose2, grid)
            xs.append(np.concatenate([m1, m2w]).astype(np.float32))
            prep.append((p, m2w, rel, cell))
        m, u = predict_masses(model.net, np.stack(xs), batch_size=batch_size)
        for k, (p, m2w, rel, cell) in enumerate(prep):
            yield FuseResult(p.id, m[k], u[k], m2w, rel, cell, xs[k][:2])


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


def load_risk(model: str | os.PathLike, *, tracking_uri: str | None = None) -> LoadedRisk:
    """Load a risk network by registry reference (``name@alias``; a bare alias means
    ``traffictwin-risk``) or model folder. Raises :class:`ApiError`."""
    from traffictwin.mlops.registry import RISK_NAME
    from traffictwin.risk.model_io import RiskModelError, load_risk_model

    name, alias, path = _split_ref(model)
    if path is None:
        cl = connect(tracking_uri)
        rm, desc = _load_registered(
            cl, name or RISK_NAME, alias, load_risk_model, "risk model", RISK_NAME
        )
    else:
        try:
            rm, desc = load_risk_model(path), str(path)
        except RiskModelError as exc:
            raise ApiError(str(exc)) from None
    check_risk_domain((rm.meta or {}).get("domain"), desc)
    return LoadedRisk(rm, desc)


def check_image_file(path: str | os.PathLike) -> tuple[int, int]:
    """``(width, height)`` (px) of an image file from its header alone: :class:`InputFileError`
    when it is missing, not a supported format or larger than the pixel limit. Cheap (nothing is
    decoded): the CLI checks every input this way before it loads a model."""
    from traffictwin.io.limits import InputError, check_image_size

    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{path}: image not found")
    try:  # format and size from the header, before a pixel is decoded
        return check_image_size(path)
    except InputError as exc:
        raise InputFileError(str(exc)) from None


def read_image(path: str | os.PathLike) -> np.ndarray:
    """An 8-bit BGR image (grayscale is expanded to 3 channels, :func:`as_bgr`); errors name the file."""
    import cv2

    path = Path(path)
    check_image_file(path)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputFileError(f"{path}: not a readable image (OpenCV could not decode it)")
    return as_bgr(img, str(path))


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
        raise InputFileError(f"params_path: {path} not found (expected a params.yaml)")
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
    rd_given = _params_risk_data(params_path) if params_path else None
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
    speed = check_speed_value(speed)
    if params_path:
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
                f"speed: {speed:g} m/s is outside the model's training range [{lo:g}, {hi:g}] m/s ({src})"
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


MIN_IMAGE_PX = 32  # the smallest image side (px) SGM and the ORB check can work on
MAX_UPSCALE = 4.0  # resize=True enlarges an image at most this much (per axis) to the camera
MAX_THW_THRESHOLD_S = 10.0  # a larger THW threshold calls almost every frame critical


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


def _frame_images(fr: Frame, risk: LoadedRisk, resize: bool) -> tuple[np.ndarray, np.ndarray]:
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
    cam = risk.domain.get("camera")
    if isinstance(cam, dict) and "width" in cam and "height" in cam:
        cw, ch = int(cam["width"]), int(cam["height"])
        if (left.shape[1], left.shape[0]) != (cw, ch):
            if not resize:
                raise ModelDomainError(
                    f"{ln}: image size {left.shape[1]}x{left.shape[0]} differs from the model's "
                    f"training camera {cw}x{ch} (W x H, domain.camera of {risk.description}); "
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


def check_thw_threshold(thw_threshold: Any, who: str = "thw_threshold") -> float:
    """A THW threshold (s): a finite number in (0, :data:`MAX_THW_THRESHOLD_S`]."""
    try:
        t = float(thw_threshold)
    except (TypeError, ValueError):
        raise InputValueError(f"{who}: expected seconds, got {thw_threshold!r}") from None
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
        raise InputValueError(f"batch_size: must be >= 1, got {batch_size}")
    check_thw_threshold(thw_threshold)
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
