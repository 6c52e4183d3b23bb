"""Stage `train_risk_hybrid`: the corridor hybrid risk predictor, one run per seed.

Reads ``risk_hybrid.*`` (features and training), ``evaluation.risk.geometric`` (the corridor
point filter shared with the rule), ``risk_data.metric`` (subject footprint), ``risk_model.label``
and ``risk_model.orb_filter``, ``seed``; data ``data/risk``, ``data/disparity``,
``data/stereo_learned``, ``data/orb/orb.csv``. Writes ``models/risk_hybrid/hybrid`` (first seed) and
``models/risk_hybrid/hybrid_s<k>`` (``model.ckpt``, ``model_meta.json``, ``history.csv``): the
training split fits, the validation loss is recorded per epoch (nothing is chosen on it here;
stage ``select_risk`` compares predictors on validation). With ``risk_hybrid.learned_disparity``
the same hybrid is also trained on the learned stereo network's disparity, one run per seed
(``hybrid_learned``, ``hybrid_learned_s<k>``): evaluated beside the others, never served.
"""

from __future__ import annotations

from dataclasses import fields, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from traffictwin.config import ConfigError, get, typed
from traffictwin.io.atomic import write_csv_atomic
from traffictwin.risk.config import EvalRiskConfig, MetricParams
from traffictwin.risk.hybrid_config import HybridConfig
from traffictwin.risk.metric import risk_to_thw
from traffictwin.risk.model_config import LABELS

from ._common import params, run_stage, setup_logging, stage_timer
from ._paths import DISPARITY, ORB_CSV, PARAMS, RISK_DATA, STEREO_LEARNED, hybrid_model_dir

if TYPE_CHECKING:
    from traffictwin.risk.source import RiskSource

HYBRID = "hybrid"
HOLDOUT = "hybrid_holdout"
LEARNED = "hybrid_learned"
_CAMERA_KEYS = ("fx", "fy", "cx", "cy", "baseline", "mount_x", "mount_height", "width", "height")


def hybrid_runs(seeds: list[int], base: str = HYBRID) -> dict[str, int]:
    """Run name → seed: ``<base>`` for the first seed, ``<base>_s<k>`` for the k-th after it."""
    return {(base if i == 0 else f"{base}_s{i}"): int(s) for i, s in enumerate(seeds)}


def holdout_runs(seeds: list[int], templates: list[str]) -> dict[str, int]:
    """The runs trained without the held-out road templates (none when no template is held out)."""
    return hybrid_runs(seeds, HOLDOUT) if templates else {}


def learned_runs(seeds: list[int], learned: bool) -> dict[str, int]:
    """The runs on the learned stereo network's disparity (none unless ``learned``)."""
    return hybrid_runs(seeds, LEARNED) if learned else {}


def hybrid_settings(p) -> tuple[HybridConfig, list[int], list[str]]:
    """``risk_hybrid``: the feature / training config, the seeds and the held-out road templates;
    errors name the key (``learned_disparity``: :func:`learned_disparity`)."""
    node = dict(get(p, "risk_hybrid", dict))
    node.pop("learned_disparity", None)
    if "disparity" in node:
        raise ConfigError(
            f"{PARAMS.name}: 'risk_hybrid.disparity' is not a setting (the served hybrid reads SGM "
            "disparity); 'risk_hybrid.learned_disparity: true' adds runs on the learned disparity"
        )
    seeds = node.pop("seeds", None)
    holdout = node.pop("holdout_templates", None)
    if not isinstance(seeds, list) or not seeds or len(set(seeds)) != len(seeds):
        raise ConfigError(
            f"{PARAMS.name}: 'risk_hybrid.seeds' must be a non-empty list of distinct integers, got {seeds!r}"
        )
    if not isinstance(holdout, list) or not all(isinstance(t, str) for t in holdout):
        raise ConfigError(
            f"{PARAMS.name}: 'risk_hybrid.holdout_templates' must be a list of road template names, got {holdout!r}"
        )
    known = {f.name for f in fields(HybridConfig)}
    unknown = sorted(set(node) - known)
    if unknown:
        raise ConfigError(
            f"{PARAMS.name}: 'risk_hybrid' has unknown key(s) {unknown} (known: {sorted(known)})"
        )
    try:
        return HybridConfig.from_dict(node), [int(s) for s in seeds], list(holdout)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{PARAMS.name}: 'risk_hybrid': {exc}") from None


def learned_disparity(p) -> bool:
    """``risk_hybrid.learned_disparity``: also train the hybrid on the learned stereo network's
    disparity (data/stereo_learned)."""
    return get(p, "risk_hybrid.learned_disparity", bool)


def _split_data(
    source: RiskSource,
    configs: dict[str, HybridConfig],
    camera: dict[str, float],
    geo: Any,
    label: str,
    holdout: list[str],
    fpath: str,
) -> dict[str, dict[str, tuple]]:
    """Per disparity source and split (train, val): ``(features, THW label (s), seen)`` with
    ``seen`` the frames not of a held-out road template."""
    from traffictwin.risk.predictors import source_features
    from traffictwin.risk.source import check_label

    data: dict[str, dict[str, tuple]] = {}
    for disparity, c in configs.items():
        data[disparity] = {}
        for split in ("train", "val"):
            x, rows = source_features(source, source.split_frames(split), camera, geo, c)
            thw = risk_to_thw(check_label(rows, label, fpath), c.thw_cap_s)
            seen = ~rows["template"].isin(holdout).to_numpy() if holdout else np.ones(len(x), bool)
            data[disparity][split] = (x, thw, seen)
    return data


def _run_meta(
    p: Any,
    run: tuple,
    label: str,
    camera: dict[str, float],
    n_train: int,
    n_val: int,
    history: list[dict],
) -> dict[str, Any]:
    """model_meta.json of one run ``(name, seed offset, held-out templates, base, disparity)``."""
    name, seed, held, base, disparity = run
    return {
        "variant": name,
        "label": label,
        "objective": "log_thw",
        "seed_offset": int(seed),
        "replicate_of": None if name == base else base,
        "holdout_templates": list(held or []),
        "disparity": disparity,
        "n_train": int(n_train),
        "n_val": int(n_val),
        "final_val_loss": history[-1].get("val_loss"),
        "domain": {
            "camera": {"width": int(camera["width"]), "height": int(camera["height"])},
            "max_speed": get(p, "risk_data.max_speed", float),
            "sgm": get(p, "risk_data.sgm", dict),
            "orb": get(p, "risk_data.orb", dict),
            "label": label,
        },
    }


def main() -> None:
    # the training's own imports (torch, pandas): the settings above are read without them
    import pandas as pd

    from traffictwin.risk.model_io import save_predictor
    from traffictwin.risk.predictors import HybridRiskModel, PredictorInputs, fit_hybrid
    from traffictwin.risk.source import RiskSource

    log = setup_logging()
    p = params()
    cfg, seeds, holdout = hybrid_settings(p)
    ev = typed(p.get("evaluation", {}).get("risk"), EvalRiskConfig, key="evaluation.risk")
    subject = typed(p.get("risk_data", {}).get("metric"), MetricParams, key="risk_data.metric")
    geo = ev.geometric.params(subject.subject_length, subject.subject_width)
    label = get(p, "risk_model.label", str, choices=LABELS)
    orb_filter = get(p, "risk_model.orb_filter", bool)
    base_seed = get(p, "seed", int, min=0)
    learned = learned_disparity(p)

    with stage_timer("train_risk_hybrid") as record:
        source = RiskSource(
            RISK_DATA,
            DISPARITY,
            ORB_CSV if orb_filter else None,
            learned_root=STEREO_LEARNED if learned else None,
        )
        camera = {k: float(source.camera[k]) for k in _CAMERA_KEYS}
        fpath = str(source.risk.root / "frames.csv")
        have = set(source.frames["template"]) if "template" in source.frames else set()
        unknown = sorted(set(holdout) - have)
        if unknown:
            raise ConfigError(
                f"{PARAMS.name}: 'risk_hybrid.holdout_templates' {unknown} are not road templates "
                f"of {fpath} (has {sorted(have)})"
            )
        configs = {"disp_sgm": cfg}
        if learned:
            configs["disp_learned"] = replace(cfg, disparity="disp_learned")
        data = _split_data(source, configs, camera, geo, label, holdout, fpath)
        if len(data["disp_sgm"]["train"][0]) == 0:
            raise ValueError(f"{fpath}: the training split has no frames (after the ORB check)")
        runs = [(n, s, None, HYBRID, "disp_sgm") for n, s in hybrid_runs(seeds).items()]
        runs += [
            (n, s, holdout, HOLDOUT, "disp_sgm") for n, s in holdout_runs(seeds, holdout).items()
        ]
        runs += [
            (n, s, None, LEARNED, "disp_learned") for n, s in learned_runs(seeds, learned).items()
        ]
        for run in runs:
            name, seed, held, _, disparity = run
            c = configs[disparity]
            xt, tt, seen_t = data[disparity]["train"]
            xv, tv, seen_v = data[disparity]["val"]
            if held:  # without the held-out templates (training and validation loss alike)
                xt, tt, xv, tv = xt[seen_t], tt[seen_t], xv[seen_v], tv[seen_v]
            net, history = fit_hybrid(xt, tt, c, base_seed + seed, xv, tv)
            meta = _run_meta(p, run, label, camera, len(xt), len(xv), history)
            out = hybrid_model_dir(name)
            model = HybridRiskModel(net, c, geo, camera, cfg=PredictorInputs(inputs=(disparity,)))
            save_predictor(model, out, meta)
            write_csv_atomic(
                out / "history.csv",
                pd.DataFrame(history),
                float_format="%.6g",
                lineterminator="\n",
            )
            log.info(
                "train_risk_hybrid: %s (seed %d%s): final train loss %.4f, val loss %.4f -> %s",
                name,
                base_seed + seed,
                f", without {held}" if held else "",
                history[-1]["train_loss"],
                history[-1].get("val_loss", np.nan),
                out,
            )
        record["runs"] = [r[0] for r in runs]
        record["n_train"] = int(len(data["disp_sgm"]["train"][0]))


if __name__ == "__main__":
    run_stage(main, "train_risk_hybrid")
