"""Latency of the `traffictwin` inference paths on this CPU (prints JSON).

    python -m benchmarks.cli_latency [--repeat 20] [--fusion-model DIR] [--risk-model DIR] [--stereo-model DIR] [--rows R --cols C]

- ``fuse`` (per pair): prealignment (SE(2) warp of map 2) and the network part
  (:func:`traffictwin.fusion.model_io.predict_masses`, batch 1: forward + evidence → masses).
- ``risk`` (per frame): ORB pair check, SGM disparity, and the network part
  (``predict`` of the network, hybrid or rule: preprocessing + forward), at batch 1 and as
  throughput at batch 64; with the learned stereo network (``--stereo-model``, else
  ``models/stereo/learned`` if trained), also its disparity per frame on SGM's map
  (:func:`traffictwin.risk.stereo_inference.learned_disparity`, batch 1) and the chain ORB + SGM +
  learned stereo + model.

Models: the given folders, else ``models/fusion/D`` / ``models/risk_shipped`` (the predictor
users get; else ``models/risk/headline``) if trained, else
networks built from params.yaml's architecture with random weights (latency does not depend on
the weights). Grid: ``--rows/--cols`` or params.yaml's grid. Medians over ``--repeat`` runs after
two warm-up runs; ``torch`` uses its default intra-op thread count (reported).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from traffictwin.threads import pin_threads

ROOT = Path(__file__).resolve().parents[1]


def _median_ms(fn: Callable[[], object], repeat: int) -> float:
    for _ in range(2):
        fn()
    ts = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        ts.append((time.perf_counter() - t) * 1e3)
    return round(float(np.median(ts)), 3)


def _shown(p: Path) -> str:
    """A model path as written into reports/benchmarks.json: relative to the repository if inside it."""
    p = p.resolve()
    return p.relative_to(ROOT).as_posix() if p.is_relative_to(ROOT) else p.name


def _fusion_model(path: str | None, cfg) -> tuple[torch.nn.Module, str]:
    from traffictwin.fusion.deeplab import DeepLabV3Plus
    from traffictwin.fusion.model_io import load_fusion_model
    from traffictwin.fusion.training import spec_from_cfg

    p = Path(path) if path else ROOT / "models" / "fusion" / "D"
    if (p / "model.ckpt").exists() or p.is_file():
        return load_fusion_model(p), _shown(p)
    torch.manual_seed(0)
    return DeepLabV3Plus(
        spec_from_cfg(cfg["fusion_model"]["architecture"])
    ).eval(), f"random weights, architecture {cfg['fusion_model'].get('name')}"


def _risk_model(path: str | None, cfg):
    from traffictwin.risk.dave2 import Dave2, Dave2Config
    from traffictwin.risk.model_io import RiskModel, load_risk_model

    shipped = ROOT / "models" / "risk_shipped"  # what `traffictwin risk` serves (select_risk)
    default = (
        shipped if (shipped / "model.ckpt").exists() else ROOT / "models" / "risk" / "headline"
    )
    p = Path(path) if path else default
    if (p / "model.ckpt").exists() or p.is_file():
        return load_risk_model(p), _shown(p)
    rm = cfg.get("risk_model", {})
    torch.manual_seed(0)
    c = Dave2Config(height=int(rm.get("height", 66)), width=int(rm.get("width", 200)))
    return RiskModel(net=Dave2(c).eval()), "random weights, DAVE-2 rgb+disp_sgm"


def _stereo_timing(path: str | None, left, right, disp, repeat: int) -> dict | None:
    """The learned stereo network's disparity per frame (ms, batch 1, refining SGM's ``disp``)
    on the pair, or None without a trained network (or one of another image size)."""
    from traffictwin.risk.stereo_inference import learned_disparity
    from traffictwin.risk.stereo_training import load_stereo_model

    p = Path(path) if path else ROOT / "models" / "stereo" / "learned"
    if not (p / "model.ckpt").exists():
        return None
    net = load_stereo_model(p)
    h, w = left.shape[:2]
    if list(net.meta.get("image_size") or [h, w]) != [h, w]:
        return None
    with torch.inference_mode():
        ms = _median_ms(
            lambda: learned_disparity(net, left[None], right[None], sgm=disp[None], batch_size=1),
            repeat,
        )
    return {"model": _shown(p), "stereo_ms_per_frame": ms}


def main(argv: list[str] | None = None) -> dict:
    import cv2
    import yaml

    from traffictwin.evidential.warp import warp_masses
    from traffictwin.fusion.model_io import predict_masses
    from traffictwin.grid import GridSpec
    from traffictwin.stereo.orb import check_pair
    from traffictwin.stereo.sgm import compute_disparity

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=20)
    ap.add_argument("--fusion-model", default=None)
    ap.add_argument("--risk-model", default=None)
    ap.add_argument("--rows", type=int, default=None)
    ap.add_argument("--cols", type=int, default=None)
    ap.add_argument("--stereo-model", default=None)
    ap.add_argument("--params", default=str(ROOT / "params.yaml"))
    ap.add_argument(
        "--threads", type=int, default=None, help="torch CPU threads (default: torch's choice)"
    )
    a = ap.parse_args(argv)
    if a.threads:
        pin_threads(a.threads)
    cfg = yaml.safe_load(Path(a.params).read_text())
    g = cfg.get("grid", {})
    grid = GridSpec(
        a.rows or int(g.get("rows", 256)),
        a.cols or int(g.get("cols", 176)),
        float(g.get("cell", 0.32)),
    )
    rng = np.random.default_rng(0)

    # ---- fuse
    net, fdesc = _fusion_model(a.fusion_model, cfg)
    mg = getattr(net, "meta", {}).get("grid") if hasattr(net, "meta") else None
    if mg and not (a.rows or a.cols):
        grid = GridSpec(int(mg["rows"]), int(mg["cols"]), float(mg["cell"]))
    d = rng.dirichlet([1, 1, 1], size=(2, grid.rows, grid.cols)).astype(np.float32)
    m1, m2 = np.moveaxis(d[0, ..., :2], -1, 0), np.moveaxis(d[1, ..., :2], -1, 0)
    rel = np.array([3.0, -1.0, 0.1])
    x = np.concatenate([m1, warp_masses(m2, rel, grid)])[None]
    with torch.inference_mode():
        warp_ms = _median_ms(lambda: warp_masses(m2, rel, grid), a.repeat)
        net_ms = _median_ms(lambda: predict_masses(net, x, batch_size=1), a.repeat)

    # ---- risk
    rmodel, rdesc = _risk_model(a.risk_model, cfg)
    cam = (cfg.get("risk_data") or {}).get("camera", {})
    w, h = int(cam.get("width", 320)), int(cam.get("height", 160))
    tex = cv2.GaussianBlur(
        cv2.resize(
            rng.integers(0, 256, size=(h // 4, (w + 16) // 4, 3), dtype=np.uint8),
            (w + 16, h),
            interpolation=cv2.INTER_NEAREST,
        ),
        (3, 3),
        0,
    )
    left, right = np.ascontiguousarray(tex[:, :w]), np.ascontiguousarray(tex[:, 6 : w + 6])
    sgm = dict((cfg.get("risk_data") or {}).get("sgm", {}))
    orb = dict((cfg.get("risk_data") or {}).get("orb", {}))
    disp = compute_disparity(left, right, **sgm)
    lb, db = np.repeat(left[None], 64, 0), np.repeat(disp[None], 64, 0)
    sp1, sp64 = np.full(1, 10.0, np.float32), np.full(64, 10.0, np.float32)  # m/s (speed models)
    with torch.inference_mode():
        orb_ms = _median_ms(lambda: check_pair(left, right, **orb), a.repeat)
        sgm_ms = _median_ms(lambda: compute_disparity(left, right, **sgm), a.repeat)
        model1_ms = _median_ms(
            lambda: rmodel.predict(left_bgr=left[None], disp_sgm=disp[None], speed=sp1), a.repeat
        )
        model64_ms = (
            _median_ms(
                lambda: rmodel.predict(left_bgr=lb, disp_sgm=db, speed=sp64, batch_size=64),
                max(3, a.repeat // 4),
            )
            / 64
        )

    stereo = _stereo_timing(a.stereo_model, left, right, disp, a.repeat)
    out = {
        "machine": {
            "cpu": platform.processor() or platform.machine(),
            "cores": os.cpu_count(),
            "torch_threads": torch.get_num_threads(),
            "torch": torch.__version__,
        },
        "fuse": {
            "model": fdesc,
            "grid": [grid.rows, grid.cols],
            "prealign_ms": warp_ms,
            "model_ms_per_pair": net_ms,
            "total_ms_per_pair": round(warp_ms + net_ms, 3),
        },
        "risk": {
            "model": rdesc,
            "image": [w, h],
            "orb_ms": orb_ms,
            "sgm_ms": sgm_ms,
            "model_ms_per_frame": model1_ms,
            "model_ms_per_frame_batch64": round(model64_ms, 3),
            "total_ms_per_frame": round(orb_ms + sgm_ms + model1_ms, 3),
        },
        "repeat": a.repeat,
    }
    if stereo is not None:
        out["risk"]["learned_stereo"] = stereo | {
            "total_ms_per_frame": round(
                orb_ms + sgm_ms + stereo["stereo_ms_per_frame"] + model1_ms, 3
            )
        }
    print(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
