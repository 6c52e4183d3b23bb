"""The twin: N vehicles' evidential maps fused into one map in a reference vehicle's frame, per time step.

A twin method is a pose source and a combination, the same pieces the fusion registry's methods
(:mod:`traffictwin.fusion.methods`) are made of, and named like them:

=====================  ==========================================  ============================
method                 pose of vehicle k in the reference frame    combination
=====================  ==========================================  ============================
``naive``              the noisy pose                              Dempster's rule
``registered``         classical registration (FM + ECC)           Dempster's rule
``learned``            the learned registration                    Dempster's rule
``dnn``                the noisy pose                              the fusion network
``registered+network`` classical registration                      the fusion network
``learned+network``    the learned registration                    the fusion network
=====================  ==========================================  ============================

Strategies (``strategy``): ``reference`` registers every other map onto the reference vehicle's
own map (one batch); ``sequential`` registers map k onto the twin built so far (everything fused
before it), in vehicle order. Either way the maps are combined in vehicle order; with Dempster's
rule (associative and commutative) the ``reference`` twin does not depend on that order.

A vehicle whose registration fails — its estimate is rejected (it does not explain the maps
better than the given pose: the fallback rule of both registrations) *and* the given pose does
not explain them either (masked occupancy correlation below the classical ``min_cc``) — is *left
out* of that step's twin, never fused with a pose known to be doubtful, and reported in
:attr:`TwinStep.used`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from traffictwin.evidential.dempster import dempster
from traffictwin.evidential.warp import warp_masses
from traffictwin.grid import GridSpec
from traffictwin.twin.methods import TWIN_METHODS, TwinMethod

__all__ = [
    "Twin",
    "TWIN_METHODS",
    "STRATEGIES",
    "TwinMethod",
    "TwinStep",
    "TwinInputError",
    "TwinOptions",
    "build_twin",
    "check_twin_inputs",
]

STRATEGIES = ("reference", "sequential")


class TwinInputError(ValueError):
    """Inputs of a twin step are inconsistent (names the input and what was expected)."""


@dataclass
class TwinStep:
    """One twin: ``masses (2, H, W)`` float32 in the reference frame; per vehicle ``used (N,)``
    (in the twin; the reference always), ``accepted (N,)`` (registration accepted; True for
    noisy-pose methods and the reference), ``poses (N, 3)`` relative pose used (x m, y m,
    yaw rad; the reference's is 0), ``seconds`` wall time of the step."""

    masses: np.ndarray
    used: np.ndarray
    accepted: np.ndarray
    poses: np.ndarray
    seconds: float


@dataclass(frozen=True)
class TwinOptions:
    """How a twin is built: the twin ``method`` (:data:`TWIN_METHODS`), the ``strategy``
    (:data:`STRATEGIES`), the ``reference`` vehicle's index, the ``models`` the method needs
    (``{"registration": ..., "fusion": ...}``) and the classical ``registration``
    (:class:`~traffictwin.fusion.registration.RegistrationParams`; default settings if None).
    An unknown method or strategy is a ValueError here."""

    method: str = "learned"
    strategy: str = "reference"
    reference: int = 0
    models: dict[str, Any] | None = None
    registration: Any = None

    def __post_init__(self) -> None:
        if self.method not in TWIN_METHODS:
            raise ValueError(
                f"twin method {self.method!r} unknown; expected one of {list(TWIN_METHODS)}"
            )
        if self.strategy not in STRATEGIES:
            raise ValueError(
                f"twin strategy {self.strategy!r} unknown; expected one of {list(STRATEGIES)}"
            )


def check_twin_inputs(
    maps: np.ndarray, rel_poses: np.ndarray, grid: GridSpec, reference: int = 0
) -> None:
    """Raise :class:`TwinInputError` unless ``maps`` is ``(N >= 2, 2, rows, cols)`` of the grid with
    finite masses and ``rel_poses`` is ``(N, 3)`` finite."""
    maps = np.asarray(maps)
    if maps.ndim != 4 or maps.shape[1] != 2:
        raise TwinInputError(
            f"maps: expected (N, 2, H, W) masses (m_F, m_O), got shape {maps.shape}"
        )
    if len(maps) < 2:
        raise TwinInputError(f"maps: a twin needs at least two vehicles, got {len(maps)}")
    if maps.shape[2:] != grid.shape:
        raise TwinInputError(
            f"maps: grid {maps.shape[2:]} differs from the grid {grid.shape} (rows, cols)"
        )
    bad = [k for k in range(len(maps)) if not np.isfinite(maps[k]).all()]
    if bad:
        raise TwinInputError(f"maps: vehicle(s) {bad} have NaN or infinite masses")
    poses = np.asarray(rel_poses, dtype=np.float64)
    if poses.shape != (len(maps), 3):
        raise TwinInputError(
            f"poses: expected ({len(maps)}, 3) (x m, y m, yaw rad) per vehicle, got {poses.shape}"
        )
    bad = [k for k in range(len(poses)) if not np.isfinite(poses[k]).all()]
    if bad:
        raise TwinInputError(f"poses: vehicle(s) {bad} have a missing (NaN) or infinite pose")
    if not 0 <= reference < len(maps):
        raise TwinInputError(f"reference: vehicle {reference} not in 0..{len(maps) - 1}")


def _register(
    method: TwinMethod,
    ref: np.ndarray,
    maps: np.ndarray,
    poses: np.ndarray,
    grid: GridSpec,
    models: dict[str, Any],
    registration: Any,
    precomputed: list[Any] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Maps ``(M, 2, H, W)`` warped into the frame of ``ref (2, H, W)`` by the pose each method
    uses, whether each registration estimate was accepted, whether the vehicle may be fused, and
    the poses ``(M, 3)`` used.

    A registering method fuses a vehicle when its estimate was accepted, or when the given pose
    itself explains the maps (masked occupancy correlation >= ``min_cc`` of the classical
    registration: at small pose errors the estimate cannot beat the given pose, which is then
    right); otherwise the vehicle is left out. Noisy-pose methods fuse every vehicle.
    ``precomputed``: the classical registration results of ``maps`` onto ``ref`` (one per map,
    :func:`traffictwin.fusion.registration_batches.register_many`), used instead of registering again."""
    from traffictwin.fusion.registration import RegistrationParams

    m = len(maps)
    if method.pose == "noisy":
        warped = np.stack([warp_masses(maps[i], poses[i], grid) for i in range(m)])
        ones = np.ones(m, bool)
        return warped.astype(np.float32), ones, ones, poses.copy()
    registration = RegistrationParams() if registration is None else registration
    if method.pose == "registered":
        from traffictwin.fusion.registration_batches import registered_fusion

        memo = keys = None
        if precomputed is not None:
            memo = {("registered", i): r for i, r in enumerate(precomputed)}
            keys = np.arange(m)
        b = registered_fusion(
            np.repeat(ref[None], m, 0), maps, poses, grid, registration, memo, keys
        )
    else:
        from traffictwin.fusion.methods import FusionInput
        from traffictwin.fusion.registration_batches import learned_registration_batch

        pre = np.stack([warp_masses(maps[i], poses[i], grid) for i in range(m)])
        inputs = np.concatenate([np.repeat(ref[None], m, 0), pre], axis=1).astype(np.float32)
        x = FusionInput(inputs=inputs, map2=maps, rel_pose_noisy=poses, grid=grid)
        b = learned_registration_batch(x, models["registration"])
    ok = b.accepted | (np.asarray(b.cc_noisy) >= registration.min_cc)
    return b.warped, b.accepted, ok, b.poses


def _combine(
    method: TwinMethod, twin: np.ndarray, warped: np.ndarray, models: dict[str, Any]
) -> np.ndarray:
    if method.combine == "dempster":
        return dempster(twin, warped).astype(np.float32)
    from traffictwin.fusion.model_io import predict_masses

    inputs = np.concatenate([twin, warped], axis=0)[None].astype(np.float32)
    return predict_masses(models["fusion"], inputs, 1)[0][0]


def build_twin(
    maps: np.ndarray,
    rel_poses: np.ndarray,
    grid: GridSpec,
    options: TwinOptions = TwinOptions(),
    shared: dict | None = None,
) -> TwinStep:
    """Fuse ``maps (N, 2, H, W)`` (each in its own sensor frame) into the frame of vehicle
    ``options.reference``; ``rel_poses (N, 3)``: each vehicle's (noisy) pose in the reference's
    frame (x m, y m, yaw rad; the reference's own row is ignored); ``options``: the method, its
    models and the rest (:class:`TwinOptions`).

    ``shared``: a dict shared by the methods built from the same maps and poses (one time step):
    with the ``reference`` strategy each pose source (classical or learned registration) then
    registers the maps once and every method using it reuses the result; the registration's wall
    time still counts in each method's ``seconds``. ``shared["registered_results"]``, if given,
    holds the classical registrations of the other vehicles onto the reference, computed
    beforehand (in parallel over a whole sequence)."""
    method, strategy, reference = options.method, options.strategy, options.reference
    registration = options.registration
    m = TWIN_METHODS[method]
    models = dict(options.models or {})
    missing = [n for n in m.needs if models.get(n) is None]
    if missing:
        raise ValueError(f"twin method {method!r} needs the model(s) {missing}")
    check_twin_inputs(maps, rel_poses, grid, reference)
    t0 = time.perf_counter()
    maps = np.asarray(maps, dtype=np.float32)
    poses_in = np.asarray(rel_poses, dtype=np.float64).copy()
    n = len(maps)
    others = [k for k in range(n) if k != reference]
    used = np.zeros(n, bool)
    accepted = np.ones(n, bool)
    poses = np.zeros((n, 3))
    used[reference] = True
    twin = maps[reference].copy()
    reused = 0.0
    if strategy == "reference":
        key = (m.pose, id(models.get("registration")))
        if shared is not None and m.pose != "noisy" and key in shared:
            warped, acc, ok, p, reused = shared[key]
        else:
            t1 = time.perf_counter()
            pre = shared.get("registered_results") if shared is not None else None
            warped, acc, ok, p = _register(
                m, maps[reference], maps[others], poses_in[others], grid, models, registration, pre
            )
            if pre is not None and m.pose == "registered":  # computed beforehand: its time counts
                reused = float(sum(r.seconds for r in pre))
            if shared is not None and m.pose != "noisy":
                shared[key] = (warped, acc, ok, p, time.perf_counter() - t1 + reused)
        for j, k in enumerate(others):
            accepted[k], poses[k] = acc[j], p[j]
            if ok[j]:
                twin = _combine(m, twin, warped[j], models)
                used[k] = True
    else:
        for k in others:
            warped, acc, ok, p = _register(
                m, twin, maps[k : k + 1], poses_in[k : k + 1], grid, models, registration
            )
            accepted[k], poses[k] = acc[0], p[0]
            if ok[0]:
                twin = _combine(m, twin, warped[0], models)
                used[k] = True
    seconds = time.perf_counter() - t0 + reused
    return TwinStep(twin.astype(np.float32), used, accepted, poses, seconds)


class Twin:
    """The twin over time: :func:`build_twin` at every time step, with its ``options`` fixed.

    ``update(t, maps, rel_poses)`` takes the time stamp (s; strictly increasing — an update out of
    order is an error naming it), the N maps and their poses in the reference frame; it returns
    the step and counts the vehicles left out (``left_out``: registration rejected) and fused
    (``fused``) over all updates."""

    def __init__(self, grid: GridSpec, options: TwinOptions = TwinOptions()) -> None:
        self.grid, self.options = grid, options
        self.last_time: float | None = None
        self.left_out = 0
        self.fused = 0

    def update(
        self, t: float, maps: np.ndarray, rel_poses: np.ndarray, shared: dict | None = None
    ) -> TwinStep:
        """Fuse the maps of time ``t`` (s) into a new twin (see :func:`build_twin`; ``shared``:
        registrations of this time step shared with other twins built from the same maps)."""
        if not np.isfinite(t):
            raise TwinInputError(f"time: must be a finite number of seconds, got {t}")
        if self.last_time is not None and t <= self.last_time:
            raise TwinInputError(
                f"time: step at t = {t:g} s is not after the previous one (t = {self.last_time:g} s); "
                "time steps must be strictly increasing"
            )
        step = build_twin(maps, rel_poses, self.grid, self.options, shared)
        self.last_time = float(t)
        others = len(step.used) - 1
        self.fused += int(step.used.sum()) - 1
        self.left_out += others - (int(step.used.sum()) - 1)
        return step
