"""Promotion-gate evaluation of fusion networks: a fixed test set and an ``evaluate(model_uri)``.

The gate (:mod:`traffictwin.mlops.gate`) re-evaluates challenger and champion with the same
callable; this one scores a registered model's fused masses with :mod:`traffictwin.fusion.metrics`
(the evaluate_fusion stage's code) on the first pairs of a prealigned split of every
configuration (the validation split: the test split is read once, by the evaluation). The gate
metric (conf/registry ``fusion.metric``) is one of its ``<split>/<name>`` numbers:
``val/kld_fou_mean`` (KLD(b), the evaluation's headline; mode min).

Models are loaded with :func:`traffictwin.mlops.registry.load_registered` (SHA-256 checked,
``weights_only`` checkpoints, no pickled code) and this problem's loaders. A model whose recorded
grid or input channels (``model_meta.json``) do not fit the test set is known-incompatible
(:func:`grid_incompatibility`): the gate records it and skips such a champion.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np


def grid_incompatibility(meta: Mapping[str, Any], inputs_shape: Sequence[int]) -> str | None:
    """Why a model whose ``model_meta.json`` is ``meta`` cannot run on inputs of ``inputs_shape``
    ``(N, C, H, W)``: its grid (rows x cols cells) or its input channels differ; ``None`` if it fits."""
    h, w = int(inputs_shape[-2]), int(inputs_shape[-1])
    g = meta.get("grid") or {}
    if not isinstance(g, Mapping) or (g.get("rows"), g.get("cols")) != (h, w):
        got = f"{g.get('rows')}x{g.get('cols')}" if isinstance(g, Mapping) else repr(g)
        return f"trained on a {got} grid, the test set is {h}x{w}"
    arch = meta.get("architecture")
    bb = arch.get("backbone") if isinstance(arch, Mapping) else None
    c = bb.get("in_channels") if isinstance(bb, Mapping) else None
    if c is not None and int(c) != int(inputs_shape[1]):
        return f"takes {c} input channels, the test set has {inputs_shape[1]}"
    return None


def first_by(order_key: np.ndarray, k: int | None) -> np.ndarray:
    """Indices of the ``k`` smallest ``order_key`` values in order (all if ``k`` is None or <= 0)."""
    idx = np.argsort(order_key, kind="stable")
    return idx if k is None or k <= 0 else idx[:k]


def _gate_arrays(
    data_roots: str | Path | Sequence[str | Path],
    split: str,
    max_pairs: int | None,
    keys: list[str],
) -> tuple[dict[str, np.ndarray], str]:
    """``keys`` of the first ``max_pairs`` pairs by ``pair_id`` of ``split`` of each prealigned
    dataset (one per pose-noise configuration), concatenated in the order given, and the
    fingerprint of the selection."""
    from traffictwin.io.shards import Dataset

    roots = [data_roots] if isinstance(data_roots, (str, Path)) else list(data_roots)
    parts, prints = [], []
    for root in roots:
        ds = Dataset(root, kind="prealigned")
        a = ds.load_all(split, keys=[*keys, "pair_id"])
        sel = first_by(np.asarray(a["pair_id"]), max_pairs)
        parts.append({k: a[k][sel] for k in keys})
        prints.append(f"{ds.manifest_hash()[:16]}:{len(sel)}")
    out = {k: np.concatenate([p[k] for p in parts]) for k in keys}
    return out, f"prealigned:{'+'.join(prints)}:{split}"


def fusion_test_set(
    data_roots: str | Path | Sequence[str | Path],
    split: str = "val",
    max_pairs: int | None = None,
) -> tuple[np.ndarray, np.ndarray, str]:
    """Gate set of prealigned datasets (one per configuration: the one network serves them all):
    ``inputs (N,4,H,W)``, ``label (N,2,H,W)`` of the first ``max_pairs`` pairs by ``pair_id`` of
    each (a fixed selection), and its fingerprint."""
    a, fp = _gate_arrays(data_roots, split, max_pairs, ["inputs", "label"])
    return (
        np.ascontiguousarray(a["inputs"], np.float32),
        np.ascontiguousarray(a["label"], np.float32),
        fp,
    )


def fusion_evaluator(
    inputs: np.ndarray, label: np.ndarray, batch_size: int = 8, split: str = "val"
) -> Callable[[str], dict[str, float]]:
    """``evaluate(model_uri)``: fused masses of the registered model on ``inputs``, scored with
    :mod:`traffictwin.fusion.metrics` as ``<split>/<name>``."""
    from traffictwin.fusion import metrics as fm
    from traffictwin.fusion.model_io import load_fusion_model, predict_masses
    from traffictwin.mlops.registry import load_registered

    def evaluate(uri: str) -> dict[str, float]:
        model = load_registered(
            uri, load_fusion_model, check=lambda meta: grid_incompatibility(meta, inputs.shape)
        )
        m, _ = predict_masses(model, inputs, batch_size=batch_size)
        agg = fm.aggregate(fm.per_sample_metrics(label, m))
        return {f"{split}/{k}": float(v) for k, v in agg.items()}

    return evaluate


def registration_test_set(
    data_roots: str | Path | Sequence[str | Path],
    split: str = "val",
    max_pairs: int | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """:func:`fusion_test_set` plus the noisy relative poses ``(N, 3)`` the learned registration needs."""
    a, fp = _gate_arrays(data_roots, split, max_pairs, ["inputs", "label", "rel_pose_noisy"])
    return (
        np.ascontiguousarray(a["inputs"], np.float32),
        np.ascontiguousarray(a["label"], np.float32),
        np.ascontiguousarray(a["rel_pose_noisy"], np.float64),
        fp + ":poses",
    )


def registration_evaluator(
    inputs: np.ndarray,
    label: np.ndarray,
    rel_pose_noisy: np.ndarray,
    batch_size: int = 8,
    split: str = "val",
) -> Callable[[str], dict[str, float]]:
    """``evaluate(model_uri)`` for a registered learned registration: its fused masses
    (``model(inputs, rel_pose_noisy)``: estimate, fallback, warp, Dempster) scored like
    :func:`fusion_evaluator`'s, as ``<split>/<name>``."""
    import torch

    from traffictwin.fusion import metrics as fm
    from traffictwin.fusion.registration_io import load_registration_model
    from traffictwin.mlops.registry import load_registered

    def evaluate(uri: str) -> dict[str, float]:
        model = load_registered(
            uri,
            load_registration_model,
            check=lambda meta: grid_incompatibility(meta, inputs.shape),
        )
        parts = []
        with torch.no_grad():
            for s in range(0, len(inputs), batch_size):
                x = torch.from_numpy(inputs[s : s + batch_size])
                p = torch.from_numpy(rel_pose_noisy[s : s + batch_size])
                parts.append(model(x, p).float().numpy())
        agg = fm.aggregate(fm.per_sample_metrics(label, np.concatenate(parts)))
        return {f"{split}/{k}": float(v) for k, v in agg.items()}

    return evaluate
