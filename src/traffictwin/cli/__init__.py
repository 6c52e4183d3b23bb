"""``traffictwin`` — the user-facing command (inference on your own files, registry, runs).

A thin layer over the public Python API :mod:`traffictwin.api` (models, fusion, risk) and
:mod:`traffictwin.export`. Global options: ``--version``, ``--threads N`` (torch CPU threads).

Subcommands::

    traffictwin fuse MAP1.npz MAP2.npz --pose1 x,y,yaw --pose2 x,y,yaw [--model REF]
                     [--tracking-uri URI] [--cell M] -o OUT [--force]
    traffictwin fuse --pairs LIST.csv|FOLDER [--model REF] [--batch-size 8] [--no-preview] -o OUTDIR
    traffictwin twin MAP1.npz MAP2.npz [MAP3.npz ...] --pose x,y,yaw --pose ... [--method ...] -o OUT
    traffictwin risk LEFT.png RIGHT.png [--speed M_S] [--model REF] [--params FILE] [--resize] [-o OUT.json]
    traffictwin risk FOLDER [--speed M_S] [--model REF] [--batch-size 16] [-o OUT.csv]
    traffictwin export fusion|risk --model REF -o MODEL.pt
    traffictwin rollback --model NAME [--version V] [--log FILE]
    traffictwin status [--model NAME ...]
    traffictwin runs compare --experiment fusion [--metrics a b ...] [--tracking-uri URI] [--wide]

Models (``--model REF``)
------------------------
A registry reference ``name@alias`` (e.g. ``traffictwin-risk@champion``) or a bare alias
(``champion`` / ``challenger``: ``traffictwin-risk`` for risk, ``traffictwin-fusion`` for
fusion: one network serves every pose-noise level), or the path of a model folder (``model.ckpt`` + ``model_meta.json``), which needs no
registry at all. The registry is ``--tracking-uri``, else ``MLFLOW_TRACKING_URI``, else the
project's ``mlflow.db`` (inside the project only); a missing database is an error, never created.
An unreachable registry is one line within seconds (MLflow's HTTP retries are bounded:
``MLFLOW_HTTP_REQUEST_MAX_RETRIES=0``, ``MLFLOW_HTTP_REQUEST_TIMEOUT=5`` unless set).

Input formats
-------------
- Evidential grid map (``fuse``): a ``.npz`` with ``m_free`` and ``m_occ``, each a ``(H, W)``
  float array of masses in the map's own sensor frame (row 0 = front/+x, col 0 = left/+y, sensor
  at the centre), on the simplex, no NaN. Optional scalar ``cell`` (m per cell) and ``pose``
  (x, y, yaw of the sensor in the world; m, m, rad). The grid (rows, cols, cell) must be the
  model's training grid.
- Poses: ``x,y,yaw`` in a common world frame, metres and **radians** (for a negative first value
  write ``--pose1=-3,2,0.1``).
- ``fuse --pairs``: a CSV with columns ``map1,map2`` and optionally ``id``, ``x1,y1,yaw1,x2,y2,yaw2``
  (else the maps' own ``pose``) and ``cell``; relative paths are relative to the CSV's folder. Or
  a FOLDER of ``<id>_1.npz`` / ``<id>_2.npz`` maps that carry their ``pose``. Output folder:
  ``<id>.npz`` (+ ``<id>.png`` unless ``--no-preview``) per pair and ``summary.csv``.
- Stereo pairs (``risk``): rectified 8-bit images readable by OpenCV of equal size, the size of
  the model's training camera (``domain.camera`` of its metadata) unless ``--resize`` (both
  images resized to it before ORB and SGM: the disparity is then in the camera's pixel scale). A
  folder holds pairs named ``<id>_left.<ext>`` / ``<id>_right.<ext>``; they are streamed in
  batches (``--batch-size``) and the result is a CSV with one row per ``<id>``. SGM/ORB settings
  are those of the model's metadata (``domain.sgm`` / ``domain.orb``), else ``risk_data.sgm`` /
  ``risk_data.orb`` of ``--params FILE``, else the library defaults.
- ``--speed`` (m/s) is checked against the model's training speed range (``domain.speed_range``
  or ``domain.max_speed`` of its metadata, else ``risk_data.max_speed`` of ``--params``); a model
  without a speed input gets a warning (the speed then only scales ``gap_m``).

Outputs
-------
``risk`` clamps the risk to [0, 1]; THW and gap are ``null`` in JSON and empty in CSV when
nothing is ahead (never ``inf``). Every command (:mod:`traffictwin.io.outputs`): an output
that is an input, a path the project keeps (model folder, MLflow store, ``src/``, ``conf/``,
``tests/``, a DVC output or DVC file), a link, device or FIFO, an existing output without
``--force``, or a directory named as output file is refused; ``--force`` replaces only a
previous output of the command's own kind, recognised by content; missing parent folders are
created; all outputs are written to temp files and moved onto their names at the end (new names
exclusively), so nothing is half-written and of two writers of one new output one wins.

Output of ``fuse``: ``OUT.npz`` with ``m_free``, ``m_occ``, ``u`` (float32, map 1's frame) and
the poses used, plus ``OUT.png``: map 1, map 2 prealigned, fused (green = m_free, red = m_occ,
grey = u; axes in metres of map 1's frame, map 1's vehicle a blue triangle). Output of ``twin``: ``OUT.npz`` with ``m_free``, ``m_occ``, ``u`` (the twin, first
map's frame), ``used`` / ``accepted`` per map, ``rel_pose_used`` / ``rel_pose_given`` (N, 3) and
``cell``, plus ``OUT.png``. Output of ``export``: a TorchScript file (:mod:`traffictwin.export`).

Promotion is not a command here: it needs the project's data, model folders and gate settings
(params.yaml), so it is a workflow of the repository (``python -m pipelines.promote``).

Errors exit with status 1 and one line naming the file/argument and the problem; Ctrl-C exits
with one line and status 130.

Layout: one module per subcommand, each holding its option table, its parser and its handler
(``fuse``, ``twin``, ``risk``, ``export``, ``registry``: rollback and status, ``runs``);
``common`` the shared options, input/output helpers and one-line error handling; ``previews``
the PNG previews; ``app`` the top-level parser and :func:`main`. Heavy libraries (torch, MLflow)
are imported inside the handlers, so ``traffictwin --help`` starts fast.
"""

from __future__ import annotations

from traffictwin.api import (  # noqa: F401 - re-exported: the CLI's helpers live in the API
    ALIASES,
    DIVISOR,
    HTTP_ENV,
    IMAGE_EXTS,
    ApiError,
    ApiWarning,
    StereoSettings,
    risk_verdict,
    stereo_settings,
)

from . import previews
from .app import build_parser, main
from .common import API_OPTIONS, CliError, csv_value, load_masses, parse_pose
from .export import cmd_export
from .fuse import cmd_fuse, read_pair_list
from .previews import mass_panels, preview_image, twin_preview
from .registry import cmd_rollback, cmd_status
from .risk import cmd_risk
from .runs import cmd_runs_compare
from .twin import cmd_twin, load_twin_models

__all__ = [
    "API_OPTIONS",
    "CliError",
    "build_parser",
    "cmd_export",
    "cmd_fuse",
    "cmd_risk",
    "cmd_rollback",
    "cmd_runs_compare",
    "cmd_status",
    "cmd_twin",
    "csv_value",
    "load_masses",
    "load_twin_models",
    "main",
    "mass_panels",
    "parse_pose",
    "preview_image",
    "previews",
    "read_pair_list",
    "twin_preview",
]
