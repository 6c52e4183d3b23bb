"""The ``python_function`` (pyfunc) side of a logged traffictwin model.

Every model :func:`traffictwin.trainer.log_model` logs is one directory with two flavours:

- ``traffictwin`` — the project's own loader (:func:`traffictwin.mlops.registry.load_registered`:
  SHA-256 check, then the problem loader);
- ``python_function`` — ``loader_module: traffictwin.mlops.serving`` and no ``code`` folder: the
  directory carries no executable code, so ``mlflow.pyfunc.load_model`` and ``mlflow models
  serve`` import this module from the *installed* ``traffictwin`` (serve with
  ``--env-manager local`` in the project's environment). :func:`_load_pyfunc` refuses a model
  logged by another ``major.minor`` of traffictwin before it reads the weights. ``requirements.txt``
  pins torch (from the PyTorch CPU index), numpy, lightning, ...; never ``traffictwin``, which no
  package index has.

Nothing is pickled: :func:`_load_pyfunc` reads ``model.ckpt`` with ``weights_only=True`` and
``model_meta.json`` through the problem's loader, exactly as the project's own loader does.
``predict`` takes the float32 array of the model's signature (the ``input_example`` logged with
it) and returns the network's raw output as float32 numpy:

- ``fusion``: ``(N, 4, H, W)`` prealigned masses -> ``(N, 2, H, W)`` evidence (free, occupied);
- ``risk``: ``(N, C[+1], h, w)`` normalised channels (+ a speed plane in m/s for speed models,
  :func:`traffictwin.risk.dave2.pack_input`) -> ``(N,)`` normalised risk;
- ``registration``: ``(N, 4, H, W)`` -> the learned registration network's output;
- ``stereo``: ``(N, 6[+1], H, W)`` left and right B, G, R planes (0-255) [+ SGM's disparity
  plane, px, for a network that refines SGM] -> ``(N, 2, H, W)`` disparity (px, -1 invalid) and
  spread (px) (:class:`traffictwin.risk.stereo_io.PackedStereo`).

The requirement list (:func:`pip_requirements`) is what this module and the problem loaders
import, pinned to the versions installed where the model was logged.

Input checks: :meth:`TrafficTwinModel.predict`
checks the input before the network runs and refuses it with an ``MlflowException`` of
``INVALID_PARAMETER_VALUE`` (``mlflow models serve`` answers HTTP 400 with the one-line reason):

- at most :func:`max_batch` samples (:data:`MAX_BATCH`; the environment variable
  ``TRAFFICTWIN_SERVE_MAX_BATCH`` of the server sets it, a request's ``"params": {"max_batch":
  n}`` can only lower it: the logged signature declares that one param, so MLflow passes it on
  and refuses a non-integer or a bool with HTTP 400; MLflow drops any other param with a log
  line before the model sees it), each of the model's shape (fusion / registration: the training grid of its
  metadata; risk: the network's or the predictor's input);
- numbers only, never bools (``true`` / ``false``), finite (a value beyond float32 counts as
  infinite);
- plausible values: masses in [0, 1] with m_F + m_O <= 1 (within :data:`MASS_TOL`); normalised
  DAVE-2 channels within ±:data:`CHANNEL_BOUND`; a speed plane constant per sample and within
  the model's training speed range (``domain.speed_range`` / ``domain.max_speed`` of its
  metadata, else [0, :data:`MAX_SPEED`] m/s); SGM disparity in [-1, image width] px; image
  planes in [0, 255] of the stereo network's training size (``image_size`` of its metadata).

An output with NaN or ±inf is never returned (HTTP 500, ``INTERNAL_ERROR``): JSON has no NaN.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

# problem -> (module, loader): looked up by name, so that logging a model (every training stage)
# does not make the stages depend on the other problems' loaders; they run where a model is served
LOADERS = {
    "fusion": ("traffictwin.fusion.model_io", "load_fusion_model"),
    "risk": ("traffictwin.risk.model_io", "load_risk_model"),
    "registration": ("traffictwin.fusion.registration_io", "load_registration_model"),
    "stereo": ("traffictwin.risk.stereo_io", "load_stereo_model"),
}
#: most samples one request may carry (``TRAFFICTWIN_SERVE_MAX_BATCH`` overrides it)
MAX_BATCH = 64
ENV_MAX_BATCH = "TRAFFICTWIN_SERVE_MAX_BATCH"
#: how far masses may leave [0, 1] and the simplex (a client's float32 round-off)
MASS_TOL = 1e-3
#: largest |value| of a normalised DAVE-2 channel: :func:`traffictwin.risk.dave2.preprocess`
#: gives RGB in [-1, 1] and disparity / disp_scale in [0, ~1]; the margin admits standardised data
CHANNEL_BOUND = 10.0
#: speed bound (m/s) of a model whose metadata records no training speed range
MAX_SPEED = 100.0
#: SGM's mark of an invalid pixel (px, :data:`traffictwin.stereo.sgm.INVALID`)
INVALID_DISPARITY = -1.0


def _refuse(message: str, *, internal: bool = False) -> Exception:
    """The ``MlflowException`` the scoring server turns into HTTP 400 (500 when ``internal``)."""
    from mlflow.exceptions import MlflowException
    from mlflow.protos.databricks_pb2 import INTERNAL_ERROR, INVALID_PARAMETER_VALUE

    return MlflowException(
        message, error_code=INTERNAL_ERROR if internal else INVALID_PARAMETER_VALUE
    )


def _first(mask: np.ndarray) -> tuple[int, ...]:
    """Index of the first True of ``mask`` (no index array of every True is built)."""
    return tuple(int(i) for i in np.unravel_index(int(np.argmax(mask)), mask.shape))


def max_batch(params: Mapping[str, Any] | None = None) -> int:
    """Most samples (N) one ``predict`` call takes: ``TRAFFICTWIN_SERVE_MAX_BATCH`` or
    :data:`MAX_BATCH`, lowered (never raised) by ``params["max_batch"]``."""
    limit = MAX_BATCH
    raw = os.environ.get(ENV_MAX_BATCH, "").strip()
    if raw:
        try:
            limit = int(raw)
        except ValueError:
            limit = 0
        if limit < 1:
            raise _refuse(
                f"{ENV_MAX_BATCH}: expected a positive integer number of samples, got {raw!r}",
                internal=True,
            )
    p = params.get("max_batch") if isinstance(params, Mapping) else None
    if p is not None:
        if isinstance(p, bool) or not isinstance(p, (int, np.integer)) or p < 1:
            raise _refuse(f"params.max_batch: expected a positive integer, got {p!r}")
        limit = min(limit, int(p))
    return limit


def _load(problem: str, folder: Path) -> tuple[Any, dict[str, Any]]:
    """The eval-mode network of ``problem`` whose forward the signature describes, and the
    model's metadata (``model_meta.json``: grid, training domain)."""
    import importlib

    if problem not in LOADERS:
        raise ValueError(f"{folder}: unknown traffictwin model problem {problem!r}")
    module, name = LOADERS[problem]
    model = getattr(importlib.import_module(module), name)(folder)
    meta = getattr(model, "meta", None)
    meta = dict(meta) if isinstance(meta, Mapping) else {}
    if problem == "risk" and (
        not hasattr(model, "net") or hasattr(model, "predict_features")
    ):  # the corridor rule / hybrid: input (N, 1 + H·W) = speed (m/s), SGM disparity (px)
        packed = importlib.import_module("traffictwin.risk.predictors").PackedPredictor
        return packed(model), meta
    if problem == "stereo":  # the network and its calibrated spread threshold, one input
        packed = importlib.import_module("traffictwin.risk.stereo_io").PackedStereo
        return packed(model, float(meta["spread_threshold_px"])).eval(), meta
    if problem == "risk":  # a RiskModel: the packed single-input network of its signature
        packed = importlib.import_module("traffictwin.risk.dave2").PackedDave2
        return packed(model.net).eval(), meta
    return model, meta


def _network(problem: str, folder: Path) -> Any:
    """The eval-mode network of ``problem`` whose forward the signature describes."""
    return _load(problem, folder)[0]


class TrafficTwinModel:
    """What ``mlflow.pyfunc.load_model`` wraps: ``predict(array) -> array`` of one network,
    its input checked first (module doc). ``meta``: the model's metadata (default: the
    ``meta`` of ``net`` or of the predictor it packs)."""

    def __init__(self, net: Any, problem: str, meta: Mapping[str, Any] | None = None) -> None:
        self.net = net
        self.problem = problem
        if meta is None:
            meta = getattr(getattr(net, "model", None), "meta", None) or getattr(net, "meta", None)
        self.meta: dict[str, Any] = dict(meta) if isinstance(meta, Mapping) else {}

    @property
    def _who(self) -> str:
        return f"{self.problem} model input"

    def predict(self, model_input: Any, params: dict[str, Any] | None = None) -> np.ndarray:
        """The network's output (float32 numpy) for ``model_input`` (float32 array, see module
        doc), after :meth:`check_input`; refuses to return NaN or ±inf."""
        import torch

        x = self.check_input(model_input, params)
        with torch.no_grad():
            y = np.asarray(self.net(torch.from_numpy(x)).float().numpy())
        bad = ~np.isfinite(y)
        if bad.any():
            raise _refuse(
                f"{self.problem} model output: the network produced {int(bad.sum())} NaN/inf "
                f"value(s) (first at index {_first(bad)}) for a finite input; no answer given",
                internal=True,
            )
        return y

    def check_input(self, model_input: Any, params: Mapping[str, Any] | None = None) -> np.ndarray:
        """``model_input`` as a C-contiguous float32 array once batch size, shape, finiteness and
        value ranges are checked (module doc); else an ``MlflowException`` (HTTP 400)."""
        who = self._who
        try:
            a = np.asarray(model_input)
        except (TypeError, ValueError) as exc:
            raise _refuse(f"{who}: not a numeric array ({type(exc).__name__})") from None
        if a.dtype.kind not in "iuf":  # never bools as numbers
            raise _refuse(f"{who}: expected a float32 array, got dtype {a.dtype}")
        if a.ndim < 2 or a.shape[0] < 1:
            raise _refuse(
                f"{who}: expected a batch (N, ...) of N >= 1 samples, got shape {a.shape}"
            )
        limit = max_batch(params)
        if a.shape[0] > limit:
            raise _refuse(
                f"{who}: batch of {a.shape[0]} samples, more than the limit of {limit} "
                f"({ENV_MAX_BATCH} of the server); split the request"
            )
        self._check_shape(a.shape)
        with np.errstate(over="ignore"):  # beyond float32: inf, refused next
            x = np.ascontiguousarray(a, dtype=np.float32)
        bad = ~np.isfinite(x)
        if bad.any():
            raise _refuse(
                f"{who}: {int(bad.sum())} NaN/inf value(s) (first at index {_first(bad)}; a "
                "value beyond float32 counts as inf); expected finite numbers"
            )
        if self.problem in ("fusion", "registration"):
            self._check_masses(x)
        elif self.problem == "risk":
            self._check_risk(x)
        elif self.problem == "stereo":
            self._check_stereo(x)
        return x

    # -- shapes ---------------------------------------------------------------------------------
    def _dave2_cfg(self) -> Any:
        return getattr(getattr(self.net, "net", None), "cfg", None)

    def _predictor_size(self) -> tuple[int, int] | None:
        h, w = getattr(self.net, "h", None), getattr(self.net, "w", None)
        ok = hasattr(self.net, "model") and isinstance(h, int) and isinstance(w, int)
        return (h, w) if ok else None

    def _check_shape(self, shape: tuple[int, ...]) -> None:
        who, got = self._who, tuple(int(s) for s in shape)
        if self.problem in ("fusion", "registration"):
            arch = self.meta.get("architecture")
            bb = arch.get("backbone") if isinstance(arch, Mapping) else None
            c = int(bb.get("in_channels", 4)) if isinstance(bb, Mapping) else 4
            grid = self.meta.get("grid")
            if isinstance(grid, Mapping) and "rows" in grid and "cols" in grid:
                rows, cols = int(grid["rows"]), int(grid["cols"])
                if len(got) != 4 or got[1:] != (c, rows, cols):
                    raise _refuse(
                        f"{who}: expected shape (N, {c}, {rows}, {cols}) = N x mass channels (map 1 "
                        f"free, occupied, map 2 free, occupied) x the training grid's rows x cols, "
                        f"got {got}"
                    )
                return
            if len(got) != 4 or got[1] != c or c % 2:
                raise _refuse(f"{who}: expected shape (N, {c}, H, W) of mass grids, got {got}")
            from traffictwin.io.limits import InputError, check_grid_cells

            try:
                check_grid_cells(got[2:], who)
            except InputError as exc:
                raise _refuse(str(exc)) from None
            return
        if self.problem == "stereo":
            c = int(getattr(self.net, "channels", 6))
            size = self.meta.get("image_size")
            hw = tuple(int(v) for v in size) if isinstance(size, (list, tuple)) else None
            if len(got) != 4 or got[1] != c or (hw is not None and got[2:] != hw):
                sgm = " + SGM disparity (px)" if c == 7 else ""
                dims = f"{hw[0]}, {hw[1]}" if hw else "H, W"
                raise _refuse(
                    f"{who}: expected shape (N, {c}, {dims}) = N x left B, G, R + right B, G, R "
                    f"(0-255){sgm} x the training images' height x width px, got {got}"
                )
            return
        if self.problem != "risk":
            return
        cfg = self._dave2_cfg()
        if cfg is not None:
            want = (
                int(cfg.in_channels) + int(bool(cfg.use_speed)),
                int(cfg.height),
                int(cfg.width),
            )
            if len(got) != 4 or got[1:] != want:
                speed = " + a speed plane (m/s)" if cfg.use_speed else ""
                raise _refuse(
                    f"{who}: expected shape (N, {want[0]}, {want[1]}, {want[2]}) = N x normalised "
                    f"channels {list(cfg.inputs)}{speed} x {want[1]} x {want[2]} px, got {got}"
                )
            return
        size = self._predictor_size()
        if size is not None and (len(got) != 2 or got[1] != 1 + size[0] * size[1]):
            raise _refuse(
                f"{who}: expected shape (N, {1 + size[0] * size[1]}) = N x (speed in m/s, then "
                f"the SGM disparity in px of {size[0]}x{size[1]}, row-major), got {got}"
            )

    # -- values ---------------------------------------------------------------------------------
    def _check_masses(self, x: np.ndarray) -> None:
        n, c, h, w = x.shape
        m = x.reshape(n, c // 2, 2, h, w)
        total = m[:, :, 0] + m[:, :, 1]
        bad = (m < -MASS_TOL).any(axis=2) | (m > 1 + MASS_TOL).any(axis=2) | (total > 1 + MASS_TOL)
        if bad.any():
            i, k, r, col = _first(bad)
            raise _refuse(
                f"{self._who}: masses outside [0, 1] or the simplex at {int(bad.sum())} cell(s) "
                f"(first: sample {i}, map {k + 1}, row {r}, col {col}; min mass "
                f"{float(m.min()):.4g}, max m_F + m_O {float(total.max()):.4g}); expected "
                f"m_F, m_O >= 0 and m_F + m_O <= 1 within {MASS_TOL:g}"
            )

    def _check_stereo(self, x: np.ndarray) -> None:
        img = x[:, :6]
        bad = (img < 0) | (img > 255)
        if bad.any():
            i, c, r, col = _first(bad)
            raise _refuse(
                f"{self._who}: image plane {c} holds {float(img[i, c, r, col]):g} at sample {i}, "
                f"row {r}, col {col} ({int(bad.sum())} value(s) refused); expected 8-bit "
                "B, G, R values in [0, 255]"
            )
        if x.shape[1] == 7:
            d = x[:, 6]
            bad = (d < INVALID_DISPARITY) | (d > x.shape[3])
            if bad.any():
                i, r, col = _first(bad)
                raise _refuse(
                    f"{self._who}: SGM disparity {float(d[i, r, col]):g} px at sample {i}, row "
                    f"{r}, col {col} ({int(bad.sum())} value(s) refused); expected values in "
                    f"[{INVALID_DISPARITY:g}, {x.shape[3]}] px ({INVALID_DISPARITY:g} = invalid)"
                )

    def _speed_range(self) -> tuple[float, float, str]:
        d = self.meta.get("domain")
        d = d if isinstance(d, Mapping) else {}
        rng = d.get("speed_range")
        if isinstance(rng, (list, tuple)) and len(rng) == 2:
            return float(rng[0]), float(rng[1]), "domain.speed_range of the model"
        if isinstance(d.get("max_speed"), (int, float)):
            return 0.0, float(d["max_speed"]), "domain.max_speed of the model"
        return 0.0, MAX_SPEED, "no training range recorded: the default bound"

    def _check_speed(self, speed: np.ndarray) -> None:
        lo, hi, src = self._speed_range()
        bad = (speed < max(lo, 0.0)) | (speed > hi)
        if bad.any():
            i = _first(bad)[0]
            raise _refuse(
                f"{self._who}: speed {float(speed[i]):g} m/s of sample {i} is outside "
                f"[{max(lo, 0.0):g}, {hi:g}] m/s ({src}); {int(bad.sum())} sample(s) refused"
            )

    def _check_risk(self, x: np.ndarray) -> None:
        who = self._who
        cfg = self._dave2_cfg()
        if cfg is not None:
            names: list[str] = []
            for group in cfg.inputs:
                names += ["r", "g", "b"] if group == "rgb" else [group]
            ch = x[:, : len(names)]
            bad = np.abs(ch) > CHANNEL_BOUND
            if bad.any():
                i, c, r, col = _first(bad)
                raise _refuse(
                    f"{who}: normalised channel '{names[c]}' holds {float(ch[i, c, r, col]):g} at "
                    f"sample {i}, row {r}, col {col} ({int(bad.sum())} value(s) beyond "
                    f"±{CHANNEL_BOUND:g}); expected RGB / 127.5 - 1 in [-1, 1] and disparity / "
                    "disp_scale >= 0 (traffictwin.risk.dave2.preprocess)"
                )
            if cfg.use_speed:
                plane = x[:, -1]
                speed = plane[:, 0, 0]
                uneven = (plane != speed[:, None, None]).any(axis=(1, 2))
                if uneven.any():
                    raise _refuse(
                        f"{who}: the speed plane (last channel) of sample {_first(uneven)[0]} is "
                        "not constant; expected the subject speed (m/s) in every cell "
                        "(traffictwin.risk.dave2.pack_input)"
                    )
                self._check_speed(speed)
            return
        size = self._predictor_size()
        if size is None:
            return
        disp = x[:, 1:]
        bad = (disp < INVALID_DISPARITY) | (disp > size[1])
        if bad.any():
            i, j = _first(bad)
            raise _refuse(
                f"{who}: SGM disparity {float(disp[i, j]):g} px at sample {i}, pixel {j} "
                f"({int(bad.sum())} value(s) refused); expected values in [{INVALID_DISPARITY:g}, "
                f"{size[1]}] px ({INVALID_DISPARITY:g} = invalid, at most the image width)"
            )
        self._check_speed(x[:, 0])


def _load_pyfunc(path: str) -> TrafficTwinModel:
    """MLflow's ``loader_module`` hook: the model of the directory ``path`` (``MLmodel`` there)."""
    from traffictwin.mlops import model_artifact as art

    folder = Path(path)
    block = art.read_flavor(folder, str(folder))
    art.check_installed_version(block, str(folder))
    problem = str(block.get("problem", ""))
    net, meta = _load(problem, folder)
    return TrafficTwinModel(net, problem, meta)
