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
  (:func:`traffictwin.fusion.refinement.refine_pose`, the classical method's ECC, coarse to fine;
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
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from traffictwin.evidential.dempster import dempster
from traffictwin.evidential.rules import cautious, yager
from traffictwin.fusion.method_input import FusionInput
from traffictwin.fusion.registration import pose_error
from traffictwin.fusion.registration_batches import (
    RegisteredBatch,
    learned_registration_batch,
    refined_registration_batch,
    registered_fusion,
)

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
]

INPUTS = ("prealigned", "raw", "pose", "model")


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
def _registered_columns(f: Fused, x: FusionInput, settings: Any) -> dict[str, np.ndarray]:
    """Per-pair diagnostics: ``reg_accepted``, residual error of the pose used
    (``reg_trans_err_m`` / ``reg_rot_err_deg``), of the raw estimate (``est_*``) and of the noisy
    pose (``noisy_*``), ``reg_success`` (residual within ``settings.success_trans_m`` and
    ``settings.success_rot_deg``), ``reg_cc_noisy`` / ``reg_cc_est``."""
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
