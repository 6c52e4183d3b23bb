"""The fusion methods registry: every way of fusing map 2 into map 1, one function each, registered once.

Every method maps a batch of pairs (:class:`FusionInput`) to fused masses ``(N, 2, H, W)`` in
map 1's frame (or a :class:`Fused` with per-pair diagnostics). Registered methods, in order:

- ``ego``: map 1 alone (what a vehicle knows without cooperation);
- ``naive``: map 2 warped by the *noisy* relative pose (the prealigned input channels 2–3), then
  Dempster's rule — the paper's baseline;
- ``naive-yager`` / ``naive-cautious``: the same warped maps combined with Yager's rule
  (conflict → unknown) or Denœux's normalised cautious rule (:mod:`traffictwin.evidential.rules`);
- ``registered``: classical registration (Fourier–Mellin + ECC) of the raw map 2 onto map 1
  starting from the noisy pose (:mod:`traffictwin.fusion.registration`), map 2 warped by the
  estimate with the project's prealignment (:func:`traffictwin.fusion.pairs.prealign`'s warp),
  then Dempster;
- ``dnn``: the fusion network of a configuration on the prealigned inputs
  (:func:`traffictwin.fusion.model_io.predict_masses`);
- ``registered+network``: ``registered``'s pose estimate and warp, then a fusion network trained
  on registered pairs (``data/registered/<cfg>``) instead of Dempster;
- ``learned``: the learned registration (:mod:`traffictwin.fusion.learned_registration`) on the
  prealigned pair, map 2 re-warped by its (accepted) estimate, then Dempster;
- ``learned+network``: the same estimate and warp, then the configuration's registered-pairs
  fusion network (model = ``(registration network, fusion network)``);
- ``learned-refined``: the learned estimate refined by ECC on the raw maps
  (:func:`traffictwin.fusion.registration.refine_pose`, the classical method's ECC, coarse to fine;
  the learned pose kept where ECC fails or moves it beyond the bound), map 2 warped by it, Dempster;
- ``learned-refined+network``: the same refined pose and warp, then the fusion network.

Use::

    from traffictwin.fusion.methods import METHODS, FusionInput, fuse
    for name, method in METHODS.items():      # registration order; method.needs says what it uses
        print(name, method.description, method.needs)
    masses = fuse("naive", FusionInput(inputs=prealigned)).masses

What a method uses (``needs``, a subset of :data:`INPUTS`): ``"prealigned"`` — the prealigned
inputs ``(N, 4, H, W)`` = [m_F1, m_O1, m_F2', m_O2']; ``"raw"`` — raw ``map1``, ``map2``
``(N, 2, H, W)`` (each in its own sensor frame), the noisy relative pose ``(N, 3)`` and the grid;
``"pose"`` — the noisy relative pose and the grid only; ``"model"`` — a trained network. ``slow`` methods are evaluated on a subset of the pairs
(``evaluation.fusion.registered_max_pairs``).

Adding a method (e.g. the hybrid ``registered+network`` or a learned registration) is one
function and one decorator::

    @register("my-method", "what it does", needs=("raw", "model"), label="legend label")
    def _my_method(x: FusionInput) -> np.ndarray | Fused: ...

The evaluation (:mod:`traffictwin.fusion.evaluation`), the figures and the findings iterate
:data:`METHODS`; a method that estimates a pose returns it in :class:`Fused` (``details``) and
may declare ``columns`` / ``summary`` hooks for its diagnostics.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from traffictwin.evidential.dempster import dempster
from traffictwin.evidential.rules import cautious, yager
from traffictwin.fusion.registration import (
    RefinementParams,
    RegistrationParams,
    RegistrationResult,
    refine_pose,
    register_pair,
)
from traffictwin.grid import GridSpec

if TYPE_CHECKING:
    import pandas as pd

__all__ = [
    "INPUTS",
    "FusionInput",
    "Fused",
    "FusionMethod",
    "METHODS",
    "register",
    "fuse",
    "RegisteredBatch",
    "registered_fusion",
    "register_prealigned",
    "refined_registration_batch",
    "parameter_grid",
    "validation_success",
]

INPUTS = ("prealigned", "raw", "pose", "model")


@dataclass
class FusionInput:
    """A batch of ``N`` pairs and what the methods may use (fields a method does not need stay None).

    ``inputs`` (N, 4, H, W) prealigned; ``map1``, ``map2`` (N, 2, H, W) raw; ``rel_pose_noisy`` /
    ``rel_pose_true`` (N, 3) relative pose of map 2's sensor in map 1's frame (x m, y m, yaw
    rad; the true one only for diagnostics); ``grid``; ``model`` (a fusion network),
    ``batch_size`` (its inference batch); ``registration`` (classical registration settings);
    ``refinement`` (the ECC refinement of the learned estimate, ``learned-refined``);
    ``pair_key`` (N,) ints naming each pair and ``memo`` a dict shared by every method run on
    these pairs: a registration (classical or learned) is then computed once per pair and reused
    by every method that uses it (``registered`` and ``registered+network``, ``learned`` and
    ``learned+network``), its wall time still counted in each method's per-pair seconds.
    """

    inputs: np.ndarray | None = None
    map1: np.ndarray | None = None
    map2: np.ndarray | None = None
    rel_pose_noisy: np.ndarray | None = None
    rel_pose_true: np.ndarray | None = None
    grid: GridSpec | None = None
    model: Any = None
    batch_size: int = 8
    registration: RegistrationParams = field(default_factory=RegistrationParams)
    refinement: RefinementParams = field(default_factory=RefinementParams)
    pair_key: np.ndarray | None = None
    memo: dict | None = None

    _ARRAYS = ("inputs", "map1", "map2", "rel_pose_noisy", "rel_pose_true", "pair_key")

    def __len__(self) -> int:
        for k in self._ARRAYS:
            v = getattr(self, k)
            if v is not None:
                return len(v)
        return 0

    def take(self, index: slice | np.ndarray) -> FusionInput:
        """The same input restricted to pairs ``index`` (a slice or an index array)."""
        arrays = {k: getattr(self, k)[index] for k in self._ARRAYS if getattr(self, k) is not None}
        return replace(self, **arrays)

    def missing(self, needs: tuple[str, ...]) -> list[str]:
        """Fields required by ``needs`` that are None."""
        req = {
            "prealigned": ("inputs",),
            "raw": ("map1", "map2", "rel_pose_noisy", "grid"),
            "pose": ("rel_pose_noisy", "grid"),
            "model": ("model",),
        }
        return [f for n in needs for f in req[n] if getattr(self, f) is None]


@dataclass
class Fused:
    """A method's output: ``masses`` (N, 2, H, W) float32; ``seconds`` (N,) per-pair wall time
    when the method times each pair itself (else None); ``details``: method-specific
    diagnostics (e.g. :class:`RegisteredBatch`)."""

    masses: np.ndarray
    seconds: np.ndarray | None = None
    details: Any = None


@dataclass(frozen=True)
class FusionMethod:
    """A registered fusion method (see the module docstring).

    ``columns(fused, x, settings)`` → extra per-pair columns of the evaluation's samples table;
    ``summary(frame, settings)`` → extra aggregate metrics; both optional.
    """

    name: str
    description: str
    needs: tuple[str, ...]
    fn: Callable[[FusionInput], np.ndarray | Fused]
    label: str
    slow: bool = False
    columns: Callable[[Fused, FusionInput, Any], dict[str, np.ndarray]] | None = None
    summary: Callable[[pd.DataFrame, Any], dict[str, float]] | None = None

    def __call__(self, x: FusionInput) -> Fused:
        miss = x.missing(self.needs)
        if miss:
            raise ValueError(
                f"fusion method {self.name!r} needs {list(self.needs)}: {miss} not given"
            )
        out = self.fn(x)
        return out if isinstance(out, Fused) else Fused(np.asarray(out, dtype=np.float32))


METHODS: dict[str, FusionMethod] = {}


def register(
    name: str,
    description: str,
    *,
    needs: tuple[str, ...],
    label: str | None = None,
    slow: bool = False,
    columns: Callable[[Fused, FusionInput, Any], dict[str, np.ndarray]] | None = None,
    summary: Callable[[pd.DataFrame, Any], dict[str, float]] | None = None,
) -> Callable[[Callable[[FusionInput], np.ndarray | Fused]], Callable]:
    """Decorator: register ``fn(x: FusionInput) -> masses | Fused`` as fusion method ``name``."""
    bad = [n for n in needs if n not in INPUTS]
    if bad:
        raise ValueError(f"register({name!r}): unknown needs {bad}; expected from {INPUTS}")

    def deco(fn: Callable[[FusionInput], np.ndarray | Fused]) -> Callable:
        if name in METHODS:
            raise ValueError(f"fusion method {name!r} is registered twice")
        METHODS[name] = FusionMethod(
            name, description, tuple(needs), fn, label or name, slow, columns, summary
        )
        return fn

    return deco


def fuse(name: str, x: FusionInput) -> Fused:
    """Run registered method ``name`` on the batch ``x``."""
    if name not in METHODS:
        raise ValueError(f"unknown fusion method {name!r} (expected one of {list(METHODS)})")
    return METHODS[name](x)


# -- prealigned baselines --------------------------------------------------------------------------
PREALIGNED = ("prealigned",)
NAIVE = "map 2 warped by the noisy pose, combined with "


def _prealigned(x: FusionInput) -> tuple[np.ndarray, np.ndarray]:
    inputs = np.asarray(x.inputs)
    if inputs.ndim != 4 or inputs.shape[1] != 4:
        raise ValueError(f"prealigned inputs must have shape (N, 4, H, W), got {inputs.shape}")
    return inputs[:, 0:2], inputs[:, 2:4]


@register("ego", "map 1 alone (no cooperation)", needs=PREALIGNED, label="ego (map 1 only)")
def _ego(x: FusionInput) -> np.ndarray:
    return np.ascontiguousarray(_prealigned(x)[0], dtype=np.float32)


@register(
    "naive", NAIVE + "Dempster's rule", needs=PREALIGNED, label="naive (noisy pose + Dempster)"
)
def _naive(x: FusionInput) -> np.ndarray:
    return dempster(*_prealigned(x))


@register("naive-yager", NAIVE + "Yager's rule", needs=PREALIGNED, label="naive + Yager")
def _naive_yager(x: FusionInput) -> np.ndarray:
    return yager(*_prealigned(x))


@register(
    "naive-cautious", NAIVE + "Denoeux's cautious rule", needs=PREALIGNED, label="naive + cautious"
)
def _naive_cautious(x: FusionInput) -> np.ndarray:
    return cautious(*_prealigned(x))


# -- registered --------------------------------------------------------------------------------------
@dataclass
class RegisteredBatch:
    """Output of :func:`registered_fusion`: fused masses, the poses used and per-pair diagnostics."""

    masses: np.ndarray  # (N, 2, H, W)
    warped: np.ndarray  # (N, 2, H, W) map 2 warped into map 1's frame by ``poses``
    poses: np.ndarray  # (N, 3) relative pose used (estimate or noisy fallback)
    estimates: np.ndarray  # (N, 3) registration estimate (even when rejected)
    accepted: np.ndarray  # (N,) bool
    cc_noisy: np.ndarray  # (N,)
    cc_est: np.ndarray  # (N,)
    seconds: np.ndarray  # (N,) wall time per pair incl. warp + Dempster (s)


def registered_fusion(
    map1: np.ndarray,
    map2: np.ndarray,
    rel_pose_noisy: np.ndarray,
    grid: GridSpec,
    params: RegistrationParams | None = None,
    memo: dict | None = None,
    keys: np.ndarray | None = None,
) -> RegisteredBatch:
    """Register each raw map 2 ``(N, 2, H, W)`` onto map 1 from the noisy pose ``(N, 3)``, warp,
    Dempster (``params``: default :class:`RegistrationParams`). ``memo`` with ``keys (N,)``: a
    pair's registration is looked up there (``("registered", key)``) or computed and stored;
    its seconds count either way."""
    from traffictwin.evidential.warp import warp_masses

    params = RegistrationParams() if params is None else params
    map1 = np.asarray(map1, dtype=np.float32)
    map2 = np.asarray(map2, dtype=np.float32)
    poses_in = np.asarray(rel_pose_noisy, dtype=np.float64).reshape(-1, 3)
    n = len(map1)
    if map2.shape != map1.shape or len(poses_in) != n:
        raise ValueError(
            f"registered_fusion: map1 {map1.shape}, map2 {map2.shape} and rel_pose_noisy {poses_in.shape} must agree on N"
        )
    out = np.empty_like(map1)
    warped = np.empty_like(map2)
    cols = {k: np.empty((n, 3)) for k in ("poses", "estimates")}
    acc = np.zeros(n, bool)
    ccn, cce, secs = np.empty(n), np.empty(n), np.empty(n)
    for i in range(n):  # per pair: OpenCV registration is inherently per image
        t0 = time.perf_counter()
        key = ("registered", int(keys[i])) if memo is not None and keys is not None else None
        if key is not None and key in memo:
            r: RegistrationResult = memo[key]
            reused = r.seconds
        else:
            r = register_pair(map1[i], map2[i], poses_in[i], grid, params)
            reused = 0.0
            if key is not None:
                memo[key] = r
        warped[i] = warp_masses(map2[i], r.pose, grid)
        out[i] = dempster(map1[i], warped[i])
        secs[i] = time.perf_counter() - t0 + reused
        cols["poses"][i], cols["estimates"][i] = r.pose, r.estimate
        acc[i], ccn[i], cce[i] = r.accepted, r.cc_noisy, r.cc_est
    return RegisteredBatch(out, warped, cols["poses"], cols["estimates"], acc, ccn, cce, secs)


_POOL_STATE: dict[str, Any] = {}  # grid and settings of :func:`register_many`'s worker processes


def _pool_init(grid: GridSpec, params: RegistrationParams) -> None:
    import signal

    import cv2

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's: it ends the pool

    cv2.setNumThreads(1)  # one process per core: OpenCV's own threads would compete
    _POOL_STATE.update(grid=grid, params=params)


def _register_task(task: tuple[int, np.ndarray, np.ndarray, np.ndarray]) -> tuple[int, Any]:
    i, m1, m2, pose = task
    return i, register_pair(m1, m2, pose, _POOL_STATE["grid"], _POOL_STATE["params"])


def register_many(
    map1: np.ndarray,
    map2: np.ndarray,
    rel_pose_noisy: np.ndarray,
    grid: GridSpec,
    params: RegistrationParams | None = None,
    workers: int = 1,
) -> list[RegistrationResult]:
    """The classical registration (:func:`register_pair`) of every pair ``(N, 2, H, W)`` from its
    noisy pose ``(N, 3)``, in ``workers`` processes (OpenCV on one thread each: the per-image
    registration does not use two cores well). The workers come from a fork server, not a fork of
    this process (whose torch / OpenCV / logging threads could hold a lock at the fork and
    deadlock the child), and each task carries its own pair. The results are the same for any
    number of workers; each result's ``seconds`` is its own single-thread wall time."""
    import multiprocessing as mp

    params = RegistrationParams() if params is None else params
    n = len(map1)
    poses = np.asarray(rel_pose_noisy, dtype=np.float64).reshape(-1, 3)
    if workers <= 1 or n <= 1:
        return [register_pair(map1[i], map2[i], poses[i], grid, params) for i in range(n)]
    tasks = ((i, map1[i], map2[i], poses[i]) for i in range(n))
    out: list[Any] = [None] * n
    ctx = mp.get_context("forkserver")
    with ctx.Pool(min(workers, n), initializer=_pool_init, initargs=(grid, params)) as pool:
        for i, r in pool.imap_unordered(_register_task, tasks, chunksize=4):
            out[i] = r
    return out


def precompute_registrations(x: FusionInput, workers: int = 1) -> None:
    """Put the classical registration of every pair of ``x`` into ``x.memo`` (keys ``x.pair_key``)
    with :func:`register_many`, so the methods that use it (``registered``,
    ``registered+network``) find it computed once, on ``workers`` cores."""
    if x.memo is None or x.pair_key is None:
        raise ValueError("precompute_registrations: x needs memo and pair_key")
    todo = [i for i, k in enumerate(x.pair_key) if ("registered", int(k)) not in x.memo]
    if not todo:
        return
    res = register_many(
        np.asarray(x.map1, dtype=np.float32)[todo],
        np.asarray(x.map2, dtype=np.float32)[todo],
        np.asarray(x.rel_pose_noisy)[todo],
        x.grid,
        x.registration,
        workers,
    )
    for i, r in zip(todo, res):
        x.memo[("registered", int(x.pair_key[i]))] = r


def register_prealigned(
    arrays: dict[str, np.ndarray], map2: np.ndarray, grid: GridSpec, params: Any = None
) -> dict[str, np.ndarray]:
    """Prealigned ``arrays`` (:func:`traffictwin.fusion.pairs.prealign_arrays`) re-warped by classical registration.

    ``map2 (N, 2, H, W)``: the raw map 2 of each pair (its own sensor frame). Map 2 is registered
    onto map 1 (``arrays["inputs"][:, :2]``) from the noisy relative pose with
    :func:`registered_fusion` (``params``: its
    :class:`~traffictwin.fusion.registration.RegistrationParams`) and warped by the pose it uses
    (the estimate, or the noisy pose where the estimate was rejected). Returns the same keys with
    ``inputs[:, 2:]`` replaced, plus ``rel_pose_registered (N, 3)`` and ``reg_accepted (N,)``.
    """
    map1 = np.asarray(arrays["inputs"][:, :2], dtype=np.float32)
    if np.shape(map2) != map1.shape:
        raise ValueError(
            f"register_prealigned: map2 {np.shape(map2)} must match map 1 {map1.shape} (N, 2, H, W)"
        )
    b = registered_fusion(map1, map2, arrays["rel_pose_noisy"], grid, params)
    out = dict(arrays)
    out["inputs"] = np.concatenate([map1, b.warped], axis=1).astype(np.float32)
    out["rel_pose_registered"] = b.poses.astype(np.float64)
    out["reg_accepted"] = b.accepted.astype(bool)
    return out


def _registered_columns(f: Fused, x: FusionInput, settings: Any) -> dict[str, np.ndarray]:
    """Per-pair diagnostics: ``reg_accepted``, residual error of the pose used
    (``reg_trans_err_m`` / ``reg_rot_err_deg``), of the raw estimate (``est_*``) and of the noisy
    pose (``noisy_*``), ``reg_success`` (residual within ``settings.success_trans_m`` and
    ``settings.success_rot_deg``), ``reg_cc_noisy`` / ``reg_cc_est``."""
    from traffictwin.fusion.registration import pose_error

    b: RegisteredBatch = f.details
    true = np.asarray(x.rel_pose_true, dtype=np.float64)
    t, r = pose_error(b.poses, true)
    te, re = pose_error(b.estimates, true)
    tn, rn = pose_error(np.asarray(x.rel_pose_noisy, dtype=np.float64), true)
    return {
        "reg_accepted": b.accepted,
        "reg_trans_err_m": t,
        "reg_rot_err_deg": r,
        "est_trans_err_m": te,
        "est_rot_err_deg": re,
        "noisy_trans_err_m": tn,
        "noisy_rot_err_deg": rn,
        "reg_success": (t <= settings.success_trans_m) & (r <= settings.success_rot_deg),
        "reg_cc_noisy": b.cc_noisy,
        "reg_cc_est": b.cc_est,
    }


def _registered_summary(f: pd.DataFrame, settings: Any) -> dict[str, float]:
    """The registration table's numbers: success rate, fallback rate (estimate rejected, noisy pose
    kept), median / 90th percentile of the residual pose error, and the noisy pose's medians."""
    return {
        "success_rate": float(f["reg_success"].mean()),
        "accepted_rate": float(f["reg_accepted"].mean()),
        "fallback_rate": float(1.0 - f["reg_accepted"].mean()),
        "residual_trans_m_p90": float(f["reg_trans_err_m"].quantile(0.9)),
        "residual_rot_deg_p90": float(f["reg_rot_err_deg"].quantile(0.9)),
        "estimate_success_rate": float(
            (
                (f["est_trans_err_m"] <= settings.success_trans_m)
                & (f["est_rot_err_deg"] <= settings.success_rot_deg)
            ).mean()
        ),
        "residual_trans_m_median": float(f["reg_trans_err_m"].median()),
        "residual_trans_m_mean": float(f["reg_trans_err_m"].mean()),
        "residual_rot_deg_median": float(f["reg_rot_err_deg"].median()),
        "noisy_trans_m_median": float(f["noisy_trans_err_m"].median()),
        "noisy_rot_deg_median": float(f["noisy_rot_err_deg"].median()),
    }


@register(
    "registered",
    "raw map 2 registered onto map 1 from the noisy pose (Fourier-Mellin + ECC), warped, Dempster",
    needs=("raw",),
    label="registered (FM + ECC) + Dempster",
    slow=True,
    columns=_registered_columns,
    summary=_registered_summary,
)
def _registered(x: FusionInput) -> Fused:
    b = registered_fusion(
        x.map1, x.map2, x.rel_pose_noisy, x.grid, x.registration, x.memo, x.pair_key
    )
    return Fused(b.masses, seconds=b.seconds, details=b)


# -- network ---------------------------------------------------------------------------------------
@register(
    "dnn",
    "the fusion network (DeepLabV3+, evidential head) on the prealigned inputs",
    needs=("prealigned", "model"),
    label="network (own config)",
)
def _network(x: FusionInput) -> np.ndarray:
    from traffictwin.fusion.model_io import predict_masses

    return predict_masses(x.model, x.inputs, x.batch_size)[0]


@register(
    "registered+network",
    "raw map 2 registered onto map 1 (Fourier-Mellin + ECC, as `registered`), warped by the "
    "estimate, then fused by a network trained on registered pairs",
    needs=("raw", "model"),
    label="registered + network",
    slow=True,
    columns=_registered_columns,
    summary=_registered_summary,
)
def _registered_network(x: FusionInput) -> Fused:
    from traffictwin.fusion.model_io import predict_masses

    b = registered_fusion(
        x.map1, x.map2, x.rel_pose_noisy, x.grid, x.registration, x.memo, x.pair_key
    )
    inputs = np.concatenate([np.asarray(x.map1, dtype=np.float32), b.warped], axis=1)
    t1 = time.perf_counter()
    masses = predict_masses(x.model, inputs, x.batch_size)[0]
    per_pair_net = (time.perf_counter() - t1) / max(1, len(inputs))
    # registration time per pair (its Dempster step included, a few % of it) + the network's share
    return Fused(masses, seconds=b.seconds + per_pair_net, details=b)


# -- learned registration ----------------------------------------------------------------------------
def learned_registration_batch(x: FusionInput, registration: Any) -> RegisteredBatch:
    """The learned registration of a batch (prealigned inputs, noisy poses): estimate, fallback,
    map 2 warped by the pose used, Dempster; as a :class:`RegisteredBatch` (per-pair seconds =
    the batch's wall time / N). Where the raw map 2 is given (``x.map2``), it is warped once from
    its own frame by the pose used (:func:`~traffictwin.evidential.warp.warp_masses`, as
    ``registered`` does); otherwise the prealigned map 2 is re-sampled by the correction.
    With ``x.memo`` and ``x.pair_key`` the batch's result is computed once (key: the pair keys)
    and reused, its per-pair seconds unchanged."""
    import torch

    from traffictwin.evidential.warp import warp_masses
    from traffictwin.fusion.learned_registration import check_pair_inputs, correction_to_pose

    key = None
    if x.memo is not None and x.pair_key is not None:
        key = ("learned", id(registration), tuple(int(k) for k in x.pair_key))
        if key in x.memo:
            return x.memo[key]
    inputs = np.ascontiguousarray(x.inputs, dtype=np.float32)
    noisy = np.asarray(x.rel_pose_noisy, dtype=np.float64)
    check_pair_inputs(inputs, noisy, x.grid)
    t0 = time.perf_counter()
    with torch.no_grad():
        r = registration.register(torch.from_numpy(inputs), torch.from_numpy(noisy))
    m, m_used = r["m"].double().numpy(), r["m_used"].double().numpy()
    poses = correction_to_pose(m_used, noisy, x.grid)
    if x.map2 is not None:
        raw2 = np.asarray(x.map2, dtype=np.float32)
        warped = np.stack([warp_masses(raw2[i], poses[i], x.grid) for i in range(len(raw2))])
    else:
        warped = r["warped"].numpy().astype(np.float32)
    masses = dempster(inputs[:, :2], warped)
    per_pair = (time.perf_counter() - t0) / max(1, len(inputs))
    out = RegisteredBatch(
        masses=masses.astype(np.float32),
        warped=warped,
        poses=poses,
        estimates=correction_to_pose(m, noisy, x.grid),
        accepted=r["accepted"].numpy().astype(bool),
        cc_noisy=r["cc_noisy"].double().numpy(),
        cc_est=r["cc_est"].double().numpy(),
        seconds=np.full(len(inputs), per_pair),
    )
    if key is not None:
        x.memo[key] = out
    return out


@register(
    "learned",
    "learned registration (cost volume over rotations x shifts on learned features, fine residual) of the "
    "prealigned map 2, re-warped by the estimate, then Dempster",
    needs=("prealigned", "pose", "model"),
    label="learned registration + Dempster",
    columns=_registered_columns,
    summary=_registered_summary,
)
def _learned(x: FusionInput) -> Fused:
    reg = x.model[0] if isinstance(x.model, tuple) else x.model
    b = learned_registration_batch(x, reg)
    return Fused(b.masses, seconds=b.seconds, details=b)


def _network_on_registered(x: FusionInput, method: str, register: Any) -> Fused:
    """The fusion network on the raw pair and map 2 warped by ``register(x, registration)``
    (a :class:`RegisteredBatch` maker); ``x.model`` = (registration network, fusion network).
    Per-pair seconds = the registration's + the network's share."""
    from traffictwin.fusion.model_io import predict_masses

    if not (isinstance(x.model, tuple) and len(x.model) == 2):
        raise ValueError(
            f"fusion method {method!r} needs model = (registration network, fusion network)"
        )
    reg, net = x.model
    b = register(x, reg)
    t1 = time.perf_counter()
    inputs = np.concatenate([np.asarray(x.inputs[:, :2], dtype=np.float32), b.warped], axis=1)
    masses = predict_masses(net, inputs, x.batch_size)[0]
    per_pair_net = (time.perf_counter() - t1) / max(1, len(inputs))
    return Fused(masses, seconds=b.seconds + per_pair_net, details=b)


@register(
    "learned+network",
    "learned registration as `learned`, then the configuration's registered-pairs fusion network "
    "instead of Dempster",
    needs=("prealigned", "pose", "model"),
    label="learned registration + network",
    columns=_registered_columns,
    summary=_registered_summary,
)
def _learned_network(x: FusionInput) -> Fused:
    return _network_on_registered(x, "learned+network", learned_registration_batch)


# -- learned registration + ECC refinement -------------------------------------------------------------
def refined_registration_batch(x: FusionInput, registration: Any) -> RegisteredBatch:
    """The learned registration's pose (:func:`learned_registration_batch`, computed once and
    shared with ``learned``) refined per pair by :func:`~traffictwin.fusion.registration.refine_pose`
    on the raw maps (``x.refinement``), map 2 warped from its own frame by the refined pose,
    Dempster. ``accepted``: the refinement was kept (else the learned pose is used); ``estimates``:
    the refined estimates (even where rejected); ``cc_noisy`` / ``cc_est``: masked correlation
    under the learned pose / the refined one. Per-pair seconds = learned share + own refinement."""
    from traffictwin.evidential.warp import warp_masses

    key = None
    if x.memo is not None and x.pair_key is not None:
        key = (
            "learned-refined",
            id(registration),
            x.refinement,
            tuple(int(k) for k in x.pair_key),
        )
        if key in x.memo:
            return x.memo[key]
    coarse = learned_registration_batch(x, registration)
    map1 = np.asarray(x.map1, dtype=np.float32)  # raw (its own frame): ECC's template
    fused1 = np.asarray(x.inputs[:, :2], dtype=np.float32)  # map 1 as `learned` fuses it
    map2 = np.asarray(x.map2, dtype=np.float32)
    n = len(map1)
    if map2.shape != map1.shape or len(coarse.poses) != n:
        raise ValueError(
            f"learned-refined: raw map1 {map1.shape} and map2 {map2.shape} must match the "
            f"{len(coarse.poses)} prealigned pairs"
        )
    out = np.empty_like(map1)
    warped = np.empty_like(map2)
    poses, estimates = np.empty((n, 3)), np.empty((n, 3))
    acc = np.zeros(n, bool)
    ccs, cce, secs = np.empty(n), np.empty(n), np.empty(n)
    for i in range(n):  # per pair: OpenCV's ECC is per image
        t0 = time.perf_counter()
        r = refine_pose(map1[i], map2[i], coarse.poses[i], x.grid, x.refinement)
        warped[i] = warp_masses(map2[i], r.pose, x.grid)
        out[i] = dempster(fused1[i], warped[i])
        secs[i] = time.perf_counter() - t0 + coarse.seconds[i]
        poses[i], estimates[i] = r.pose, r.estimate
        acc[i], ccs[i], cce[i] = r.accepted, r.cc_start, r.cc_est
    b = RegisteredBatch(out, warped, poses, estimates, acc, ccs, cce, secs)
    if key is not None:
        x.memo[key] = b
    return b


@register(
    "learned-refined",
    "learned registration as `learned`, its pose refined by ECC on the raw maps (coarse to fine, "
    "bounded; the learned pose kept where ECC fails), map 2 re-warped, then Dempster",
    needs=("prealigned", "raw", "model"),
    label="learned registration + ECC + Dempster",
    columns=_registered_columns,
    summary=_registered_summary,
)
def _learned_refined(x: FusionInput) -> Fused:
    reg = x.model[0] if isinstance(x.model, tuple) else x.model
    b = refined_registration_batch(x, reg)
    return Fused(b.masses, seconds=b.seconds, details=b)


@register(
    "learned-refined+network",
    "learned registration refined by ECC as `learned-refined`, then the fusion network instead of "
    "Dempster",
    needs=("prealigned", "raw", "model"),
    label="learned registration + ECC + network",
    columns=_registered_columns,
    summary=_registered_summary,
)
def _learned_refined_network(x: FusionInput) -> Fused:
    return _network_on_registered(x, "learned-refined+network", refined_registration_batch)


# -- choosing registration settings on validation pairs -----------------------------------------------
def parameter_grid(base: Any, grid: dict[str, list[Any]]) -> list[Any]:
    """Every combination of ``grid`` (field → candidate values, in order: the first value of each
    field varies slowest) applied to the frozen settings dataclass ``base``
    (:class:`RegistrationParams`, :class:`RefinementParams`); ``[base]`` for an empty grid."""
    import itertools

    fields = set(getattr(base, "__dataclass_fields__", {}))
    bad = sorted(set(grid) - fields)
    if bad:
        raise ValueError(
            f"parameter_grid: {bad} are not fields of {type(base).__name__} (has {sorted(fields)})"
        )
    keys = list(grid)
    return [
        replace(base, **dict(zip(keys, values)))
        for values in itertools.product(*(list(grid[k]) for k in keys))
    ]


def validation_success(
    kind: str,
    inputs: list[FusionInput],
    candidates: list[Any],
    success_trans_m: float,
    success_rot_deg: float,
    registration: Any = None,
    workers: int = 1,
) -> np.ndarray:
    """Registration success rate (residual ≤ ``success_trans_m`` and ≤ ``success_rot_deg``,
    pooled over every pair of ``inputs``) of each candidate setting: ``kind`` ``"registered"``
    (candidates :class:`RegistrationParams`, :func:`register_many` on ``workers`` cores) or
    ``"learned-refined"`` (candidates :class:`RefinementParams` refining the learned network
    ``registration``'s pose, computed once per input and shared). Each input needs raw maps and
    ``rel_pose_true``. Returns ``(len(candidates),)`` rates."""
    from traffictwin.fusion.registration import pose_error

    if kind not in ("registered", "learned-refined"):
        raise ValueError(
            f"validation_success: kind must be 'registered' or 'learned-refined', got {kind!r}"
        )
    if kind == "learned-refined" and registration is None:
        raise ValueError(
            "validation_success: 'learned-refined' needs the learned registration network"
        )
    true = np.concatenate([np.asarray(x.rel_pose_true, dtype=np.float64) for x in inputs])
    rates = np.empty(len(candidates))
    for j, params in enumerate(candidates):
        if kind == "registered":  # every input's pairs in one pool of workers
            res = register_many(
                np.concatenate([x.map1 for x in inputs]),
                np.concatenate([x.map2 for x in inputs]),
                np.concatenate([x.rel_pose_noisy for x in inputs]),
                inputs[0].grid,
                params,
                workers,
            )
            poses = np.stack([r.pose for r in res])
        else:
            for x in inputs:
                x.refinement = params
            poses = np.concatenate(
                [refined_registration_batch(x, registration).poses for x in inputs]
            )
        t, r = pose_error(poses, true)
        rates[j] = float(((t <= success_trans_m) & (r <= success_rot_deg)).mean())
    return rates
