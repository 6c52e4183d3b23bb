"""Outputs of the fusion evaluation (JSON-safe values: :func:`traffictwin.io.jsonio.json_clean`):
DVC plot data, the figures (Figs. 4–7; Fig. 4's panels recomputed for one pair), the flat numbers
of one network's MLflow run and every method's numbers as one table artifact."""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from traffictwin.fusion.config import PoseNoise
from traffictwin.fusion.evaluation.keys import (
    CROSS_ROWS,
    NETWORK,
    SCORE_KEYS,
    SCORE_METHODS,
)
from traffictwin.fusion.evaluation.loop import Evaluation
from traffictwin.grid import GridSpec

if TYPE_CHECKING:  # pandas loads where a table is built: check_params imports this package
    import pandas as pd


def qualitative_panels(
    ev: Evaluation,
    noise: Mapping[str, PoseNoise],
    grid: GridSpec,
    pair: int,
    fraction: float,
) -> dict[str, list[np.ndarray]]:
    """Fig. 4 panels (label / naive / network, one per configuration) of evaluated pair ``pair``:
    map 2 prealigned with a pose error of ``fraction``·(r, r, α) of each configuration."""
    from traffictwin.config import ConfigError
    from traffictwin.evidential.dempster import dempster
    from traffictwin.fusion.model_io import predict_masses
    from traffictwin.fusion.pairs import prealign

    if pair >= len(ev.raw["map1"]):
        raise ConfigError(
            f"params.yaml: 'evaluation.fusion.qualitative_pair' = {pair} but only "
            f"{len(ev.raw['map1'])} pairs are evaluated"
        )
    m1, m2 = ev.raw["map1"][pair], ev.raw["map2"][pair]
    pose1, pose2 = ev.raw["pose1"][pair], ev.raw["pose2"][pair]
    k = fraction
    rows: dict[str, list[np.ndarray]] = {"label": [], "naive": [], "network": []}
    for c in ev.data:
        r, alpha = noise[c].r, noise[c].alpha
        err = np.array([k * r, k * r, np.radians(k * alpha)])
        warped, _ = prealign(m2, pose1, pose2, grid, noise=err)
        inputs = np.concatenate([m1, warped])[None].astype(np.float32)
        rows["label"].append(ev.raw["label"][pair])
        rows["naive"].append(np.asarray(dempster(m1, warped)))
        rows["network"].append(predict_masses(ev.networks[NETWORK][c], inputs, 1)[0][0])
    return rows


def _rows(ev: Evaluation, base: Sequence[str]) -> list[str]:
    """``base`` methods plus every network row of ``ev`` not among them (variants, in order)."""
    return [*base, *(r for r in ev.networks if r not in base)]


def plot_tables(ev: Evaluation, noise: Mapping[str, PoseNoise]) -> dict[str, pd.DataFrame]:
    """DVC plot data: ``fusion_kld`` (per pair), ``fusion_scores`` (per configuration and row),
    ``fusion_pose_bins`` (per bin)."""
    import pandas as pd

    samples = ev.samples
    main = samples[~samples["method"].str.startswith(f"{NETWORK}-")]
    score_rows = []
    for c in ev.data:
        row: dict[str, Any] = {
            "config": c,
            "noise_r_m": noise[c].r,
            "noise_alpha_deg": noise[c].alpha,
        }
        for m in _rows(ev, SCORE_METHODS):
            for key in SCORE_KEYS:
                row[f"{m}_{key}"] = ev.metrics["test"][c].get(m, {}).get(key)
        score_rows.append(row)
    return {
        "fusion_kld": main[
            ["config", "method", "pair_id", "kld_fou", "kld_fo", "trans_err_m", "rot_err_deg"]
        ],
        "fusion_scores": pd.DataFrame(score_rows),
        "fusion_pose_bins": ev.bins,
    }


def figure_inputs(
    ev: Evaluation,
    noise: Mapping[str, PoseNoise],
    grid: GridSpec,
    pair: int,
    fraction: float,
) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """What :func:`traffictwin.fusion.evaluation_figures.evaluation_figures` needs beside fusion.json and
    the ``fusion_kld`` plot table: Fig. 4's panels (:func:`qualitative_panels`; arrays
    ``label`` / ``naive`` / ``network``: one (2, H, W) map per configuration) and the metadata
    (configurations in order, their noise (r m, α deg), the network rows, the pair shown, the
    pose-error ``fraction``, the cell size m)."""
    panels = qualitative_panels(ev, noise, grid, pair, fraction)
    configs = list(ev.data)
    meta = {
        "configs": configs,
        "noise": {c: [noise[c].r, noise[c].alpha] for c in configs},
        "network_rows": list(ev.networks),
        "pair_id": int(ev.data[configs[0]]["pair_id"][pair]),
        "fraction": float(fraction),
        "cell_m": float(grid.cell),
    }
    return {k: np.stack(v).astype(np.float32) for k, v in panels.items()}, meta


def _mlflow_key(key: str) -> str:
    """MLflow metric names allow letters, digits, ``_ - . / `` and space: others become ``_``."""
    return re.sub(r"[^\w\-./ ]", "_", key)


def _flat_row(vals: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """One row's numbers with intervals ``<k>_ci: {lo, hi}`` as ``<k>_ci_lo`` / ``<k>_ci_hi``."""
    flat: dict[str, Any] = {}
    for k, v in vals.items():
        if isinstance(v, Mapping):
            flat.update({f"{prefix}{k}_{kk}": vv for kk, vv in v.items()})
        else:
            flat[f"{prefix}{k}"] = v
    return flat


def mlflow_metrics(
    metrics: Mapping[str, Any], cfg: str, row: str = NETWORK, prefix: str = "test/"
) -> dict[str, float]:
    """The flat numbers of the MLflow run of row ``row``'s network at configuration ``cfg``:
    ``<prefix><k>`` (that network only; the other methods go to :func:`methods_table`),
    ``cross_<other>/<k>`` (the network on other configurations; rows of :data:`CROSS_ROWS`
    only); intervals ``<k>_ci`` as ``<k>_ci_lo`` / ``<k>_ci_hi``; finite values only, names
    MLflow-safe."""
    flat = _flat_row(metrics["test"][cfg].get(row, {}), prefix)
    if row in CROSS_ROWS:
        for other, vals in metrics["cross"].get(f"{row}-{cfg}", {}).items():
            flat.update({f"cross_{other}/{k}": v for k, v in vals.items()})
    out: dict[str, float] = {}
    for k, v in flat.items():
        if (
            isinstance(v, (bool, int, float, np.number))
            and v is not None
            and math.isfinite(float(v))
        ):
            out[_mlflow_key(k)] = float(v)
    return out


def methods_table(metrics: Mapping[str, Any], cfg: str) -> pd.DataFrame:
    """Every method's and network row's test numbers at configuration ``cfg``, one row each
    (column ``method`` first, then the metrics sorted; intervals as ``<k>_ci_lo`` / ``<k>_ci_hi``;
    missing or non-finite values empty): the baselines' table artifact of a network's run."""
    import pandas as pd

    rows = [{"method": m, **_flat_row(vals)} for m, vals in metrics["test"][cfg].items()]
    frame = pd.DataFrame(rows)
    cols = ["method", *sorted(c for c in frame.columns if c != "method")]
    return frame[cols]
