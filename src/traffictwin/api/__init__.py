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

Training domain: inputs outside what the model was trained on are refused
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

Verdict
    A pair that fails the ORB pair check (no reliable match: uniform or textureless images; no
    disparity; a vertical offset; swapped cameras: the median signed disparity of the reliable
    matches is negative) has no verdict: ``verdict`` is ``"unknown"`` (:data:`UNKNOWN`),
    ``critical`` ``None`` and ``verdict_reason`` names the failed rule; never "uncritical".

Arguments
    Every public function checks its arguments at the call and raises an :class:`ApiError`
    subclass naming the argument and what was expected (a bool is not a number, 2.5 is not a
    batch size); :func:`fuse` and :func:`assess_risk` check their items as they come.

THW
    Rows carry ``thw_s`` (s) and ``gap_m`` (m) as Python floats, ``inf`` when nothing is ahead
    (risk 0). The CLI writes them as ``null`` in JSON and as an empty field in CSV (one rule for
    every non-finite value), never as ``inf``.

Modules: :mod:`~traffictwin.api.errors` (the error classes), :mod:`~traffictwin.api.registry`
(tracking URI, model references), :mod:`~traffictwin.api.inputs` (poses, cells, masses, speeds),
:mod:`~traffictwin.api.fusion`, :mod:`~traffictwin.api.images` (stereo image files),
:mod:`~traffictwin.api.pairs` (a pair's images, SGM / ORB settings and check fields),
:mod:`~traffictwin.api.risk`, :mod:`~traffictwin.api.stereo` (disparity of a pair: SGM or the learned
stereo network), :mod:`~traffictwin.api.serving` (the serving app's ``POST /risk``, not imported
here); every name is used as ``api.<name>``.

This package imports only NumPy at import time; torch, OpenCV and MLflow are imported by the
functions that need them (``traffictwin --help`` stays fast).
"""

from __future__ import annotations

from .errors import ApiError, ApiWarning, InputFileError, InputValueError, ModelDomainError
from .fusion import (  # noqa: F401 - the ones not in __all__ are used as api.<name>
    DIVISOR,
    FusePair,
    FuseResult,
    FusionModel,
    check_fusion_domain,
    check_relative_pose,
    fuse,
    load_fusion,
    load_masses,
)
from .images import (  # noqa: F401 - the ones not in __all__ are used as api.<name>
    IMAGE_EXTS,
    MIN_IMAGE_PX,
    Frame,
    as_bgr,
    check_image_file,
    frames_in_folder,
    read_image,
)
from .inputs import (  # noqa: F401 - the ones not in __all__ are used as api.<name>
    SIMPLEX_TOL,
    check_cell,
    check_count,
    check_mass_grids,
    check_pose,
    check_speed_value,
)
from .registry import ALIASES, HTTP_ENV, connect, resolve_tracking_uri  # noqa: F401 - as above
from .risk import (  # noqa: F401 - the ones not in __all__ are used as api.<name>
    MAX_THW_THRESHOLD_S,
    MAX_UPSCALE,
    PACKAGED_STEREO,
    UNKNOWN,
    LoadedRisk,
    StereoSettings,
    answered_by,
    assess_risk,
    check_risk_domain,
    check_speed,
    check_thw_threshold,
    decision_cut,
    load_risk,
    risk_verdict,
    speed_range,
    stereo_settings,
)
from .stereo import (  # noqa: F401 - the ones not in __all__ are used as api.<name>
    SOURCE_KEYS,
    DisparityResult,
    LoadedStereo,
    disparity_of_pair,
    load_stereo,
)

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
    "LoadedStereo",
    "answered_by",
    "assess_risk",
    "check_cell",
    "check_mass_grids",
    "check_pose",
    "check_speed_value",
    "connect",
    "disparity_of_pair",
    "frames_in_folder",
    "fuse",
    "load_fusion",
    "load_masses",
    "load_risk",
    "load_stereo",
    "read_image",
    "resolve_tracking_uri",
]
