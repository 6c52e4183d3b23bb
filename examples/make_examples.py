"""Regenerate the sample inputs under ``examples/`` from the project's simulator (fixed seed).

Usage (repository root, ``.venv`` active)::

    python examples/make_examples.py            # rewrites examples/fuse and examples/risk
    python examples/make_examples.py --out DIR  # writes the same files under DIR instead

Every file is byte-for-byte reproducible (same code, same conf/): ``tests/test_examples.py``
regenerates them and compares.

- ``fuse/<profile>/map1.npz``, ``map2.npz`` (``profile`` = ``default`` and ``ci``: their grids
  differ): the two subject vehicles' evidential grid maps of one simulated encounter, each in its
  own sensor frame, on that profile's grid, lidar and inverse sensor model — the inputs of
  ``traffictwin fuse`` (``m_free``, ``m_occ`` float32 ``(H, W)``, ``cell`` in m).
  ``poses.json``: ``pose1`` (vehicle 1's world pose) and ``pose2`` (vehicle 2's pose as its own
  localisation reports it: the true pose plus one draw of configuration D's pose noise), as the
  ``x,y,yaw`` strings the CLI takes (m, m, rad), plus the true ``pose2_true`` and the metadata.
- ``risk/000_left.png``, ``000_right.png``: one rectified 8-bit stereo pair of the hood camera
  (default profile's camera; the ``ci`` profile uses the same one), a fault-free frame with a
  critical corridor time headway; ``000.json``: the subject's speed (``--speed``) and the
  simulator's labels of that frame.
"""

from __future__ import annotations

import argparse
import io
import math
import sys
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: make `pipelines` importable
    sys.path.insert(0, str(ROOT))

#: data seed of the examples: not the training data's (conf `seed`), so no example is a training pair
SEED = 17017
#: fusion example: scenario index and encounter; map 1 = subject 0, map 2 = subject 1
SCENARIO, ENCOUNTER = 3, 0
#: pose-noise configuration whose noise the reported pose 2 carries
NOISE_CONFIG = "D"
#: profiles that get their own grids (their `grid` differs); the stereo pair is the same for all
FUSE_PROFILES = ("default", "ci")
#: stereo example: the first fault-free frame with a critical corridor THW among these sequences
RISK_SEQUENCES = 40
#: decimals of the pose strings (mm, µrad)
POSE_DECIMALS = 3


def profile_config(profile: str) -> Any:
    """``conf/`` composed for ``profile`` (what ``make params`` / ``dvc exp run -S profile=...`` give)."""
    from traffictwin.config import compose_config

    return OmegaConf.create(compose_config(ROOT / "conf", [f"profile={profile}"]))


def pose_text(pose: np.ndarray) -> str:
    """``x,y,yaw`` as the CLI's ``--pose1`` / ``--pose2`` take it (m, m, rad)."""
    return ",".join(f"{float(v):.{POSE_DECIMALS}f}" for v in pose)


def fusion_example(cfg: Any) -> tuple[dict[str, dict[str, np.ndarray]], dict[str, Any]]:
    """Both maps (``{"map1": {...}, "map2": {...}}`` arrays for the ``.npz``) and ``poses.json``."""
    from traffictwin.evidential.noise import apply_pose_noise, scale_noise, standard_normal_draws
    from traffictwin.fusion.config import fusion_data_config, grid_config, pose_configurations
    from traffictwin.fusion.pairs import scenario_maps, template_of

    grid = grid_config(cfg)
    fd = fusion_data_config(cfg)
    p = fd.params(grid)
    sm = scenario_maps(SEED, SCENARIO, p)
    maps, poses = sm["maps"][ENCOUNTER], sm["poses"][ENCOUNTER]
    # poses as the CLI will read them back (rounded strings), noise added to the rounded true pose
    pose1 = np.array([float(v) for v in pose_text(poses[0]).split(",")])
    pose2_true = np.array([float(v) for v in pose_text(poses[1]).split(",")])
    noise_cfg = pose_configurations(cfg)[NOISE_CONFIG]
    pair_id = SCENARIO * 1000 + 2 * ENCOUNTER
    noise = scale_noise(
        standard_normal_draws(SEED, np.array([pair_id]))[0], noise_cfg.r, noise_cfg.alpha
    )
    pose2 = apply_pose_noise(pose2_true, noise)
    arrays = {
        f"map{k + 1}": {
            "m_free": maps[k, 0].astype(np.float32),
            "m_occ": maps[k, 1].astype(np.float32),
            "cell": np.float64(grid.cell),
        }
        for k in range(2)
    }
    meta = {
        "pose1": pose_text(pose1),
        "pose2": pose_text(pose2),
        "pose2_true": pose_text(pose2_true),
        "pose_units": "x m, y m, yaw rad (world frame)",
        "noise_config": NOISE_CONFIG,
        "noise_r_m": float(noise_cfg.r),
        "noise_alpha_deg": float(noise_cfg.alpha),
        "profile": str(cfg.profile.name),
        "grid": {"rows": grid.rows, "cols": grid.cols, "cell": grid.cell},
        "seed": SEED,
        "scenario": SCENARIO,
        "encounter": ENCOUNTER,
        "template": template_of(SCENARIO, p.templates),
        "time_s": float(sm["times"][ENCOUNTER]),
        "distance_m": round(float(np.hypot(*(poses[1, :2] - poses[0, :2]))), 3),
    }
    return arrays, meta


def risk_example(cfg: Any) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """The stereo pair (BGR uint8 left, right) and its metadata."""
    from pipelines.generate_risk import read_config
    from traffictwin.risk.dataset import make_shard

    _, spec, _ = read_config(cfg)
    for seq in range(RISK_SEQUENCES):
        arrays, rows = make_shard(SEED, seq, spec)
        for k, row in enumerate(rows):
            thw = float(row["thw_corridor"])
            if row["fault"] == "none" and math.isfinite(thw) and row["critical"]:
                meta = {
                    "speed_m_s": round(float(row["speed"]), 3),
                    "thw_corridor_s": round(thw, 3),
                    "thw_paper_s": _finite(row["thw_paper"]),
                    "critical": bool(row["critical"]),
                    "risk_thw_corridor": round(float(row["risk_thw_corridor"]), 6),
                    "situation": str(row["situation"]),
                    "template": str(row["template"]),
                    "seed": SEED,
                    "sequence": seq,
                    "frame": k,
                    "fault": "none",
                    "camera": spec.camera.intrinsics(),
                }
                return arrays["left"][k], arrays["right"][k], meta
    raise RuntimeError(
        f"no fault-free critical frame in the first {RISK_SEQUENCES} sequences of seed {SEED}"
    )


def _finite(x: Any) -> float | None:
    x = float(x)
    return round(x, 3) if math.isfinite(x) else None


def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """A compressed ``.npz`` with fixed zip metadata (byte-reproducible), 0-d arrays kept 0-d
    (``cell`` is a scalar, as ``traffictwin fuse`` expects)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for key in sorted(arrays):
            arr = io.BytesIO()
            np.lib.format.write_array(arr, np.asarray(arrays[key], order="C"), allow_pickle=False)
            info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.external_attr = 0o644 << 16
            zf.writestr(info, arr.getvalue(), compress_type=zipfile.ZIP_DEFLATED, compresslevel=9)
    return buf.getvalue()


def write_examples(out: Path) -> list[Path]:
    """Write every example file under ``out``; returns the paths written."""
    import cv2

    from traffictwin.io.atomic import write_bytes_atomic, write_json_atomic

    written = []
    for profile in FUSE_PROFILES:
        arrays, meta = fusion_example(profile_config(profile))
        folder = out / "fuse" / profile
        folder.mkdir(parents=True, exist_ok=True)
        for name, arr in arrays.items():
            write_bytes_atomic(folder / f"{name}.npz", npz_bytes(arr))
            written.append(folder / f"{name}.npz")
        write_json_atomic(folder / "poses.json", meta)
        written.append(folder / "poses.json")
    left, right, meta = risk_example(profile_config("default"))
    folder = out / "risk"
    folder.mkdir(parents=True, exist_ok=True)
    for side, img in (("left", left), ("right", right)):
        ok, png = cv2.imencode(".png", img)
        if not ok:
            raise RuntimeError(f"could not encode the {side} image as PNG")
        write_bytes_atomic(folder / f"000_{side}.png", png.tobytes())
        written.append(folder / f"000_{side}.png")
    write_json_atomic(folder / "000.json", meta)
    written.append(folder / "000.json")
    return written


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=ROOT / "examples", help="output folder")
    args = ap.parse_args(argv)
    for path in write_examples(args.out):
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
