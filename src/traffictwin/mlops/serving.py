"""The ``python_function`` (pyfunc) side of a logged traffictwin model (issue 17, item 7).

Every model :func:`traffictwin.trainer.log_model` logs is one directory with two flavours:

- ``traffictwin`` — the project's own loader (:func:`traffictwin.mlops.registry.load_registered`:
  SHA-256 check, then the problem loader);
- ``python_function`` — ``loader_module: traffictwin.mlops.serving`` with ``code: code``: the
  directory carries the ``traffictwin`` package source under ``code/traffictwin`` (MLflow puts
  ``code/`` on ``sys.path`` before it imports this module), so ``mlflow.pyfunc.load_model`` and
  ``mlflow models serve`` work in an environment that has only the pinned requirements of
  ``requirements.txt`` (torch from the PyTorch CPU index, numpy, lightning, ...; never
  ``traffictwin``, which no package index has).

Nothing is pickled: :func:`_load_pyfunc` reads ``model.ckpt`` with ``weights_only=True`` and
``model_meta.json`` through the problem's loader, exactly as the project's own loader does.
``predict`` takes the float32 array of the model's signature (the ``input_example`` logged with
it) and returns the network's raw output as float32 numpy:

- ``fusion``: ``(N, 4, H, W)`` prealigned masses -> ``(N, 2, H, W)`` evidence (free, occupied);
- ``risk``: ``(N, C[+1], h, w)`` normalised channels (+ a speed plane in m/s for speed models,
  :func:`traffictwin.risk.dave2.pack_input`) -> ``(N,)`` normalised risk;
- ``registration``: ``(N, 4, H, W)`` -> the learned registration network's output.

The requirement list (:func:`pip_requirements`) is what this module and the problem loaders
import, pinned to the versions installed where the model was logged.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

# problem -> (module, loader): looked up by name, so that logging a model (every training stage)
# does not make the stages depend on the other problems' loaders; they run where a model is served
LOADERS = {
    "fusion": ("traffictwin.fusion.model_io", "load_fusion_model"),
    "risk": ("traffictwin.risk.model_io", "load_risk_model"),
    "registration": ("traffictwin.fusion.registration_training", "load_registration_model"),
}


def _network(problem: str, folder: Path) -> Any:
    """The eval-mode network of ``problem`` whose forward the signature describes."""
    import importlib

    if problem not in LOADERS:
        raise ValueError(f"{folder}: unknown traffictwin model problem {problem!r}")
    module, name = LOADERS[problem]
    model = getattr(importlib.import_module(module), name)(folder)
    if problem == "risk" and (
        not hasattr(model, "net") or hasattr(model, "predict_features")
    ):  # the corridor rule / hybrid: input (N, 1 + H·W) = speed (m/s), SGM disparity (px)
        return importlib.import_module("traffictwin.risk.predictors").PackedPredictor(model)
    if problem == "risk":  # a RiskModel: the packed single-input network of its signature
        packed = importlib.import_module("traffictwin.risk.dave2").PackedDave2
        return packed(model.net).eval()
    return model


class TrafficTwinModel:
    """What ``mlflow.pyfunc.load_model`` wraps: ``predict(array) -> array`` of one network."""

    def __init__(self, net: Any, problem: str) -> None:
        self.net = net
        self.problem = problem

    def predict(self, model_input: Any, params: dict[str, Any] | None = None) -> np.ndarray:
        """The network's output (float32 numpy) for ``model_input`` (float32 array, see module doc)."""
        import torch

        x = torch.from_numpy(np.ascontiguousarray(np.asarray(model_input), dtype=np.float32))
        with torch.no_grad():
            return self.net(x).float().numpy()


def _load_pyfunc(path: str) -> TrafficTwinModel:
    """MLflow's ``loader_module`` hook: the model of the directory ``path`` (``MLmodel`` there)."""
    from traffictwin.mlops import model_artifact as art

    folder = Path(path)
    problem = str(art.read_flavor(folder, str(folder)).get("problem", ""))
    return TrafficTwinModel(_network(problem, folder), problem)
