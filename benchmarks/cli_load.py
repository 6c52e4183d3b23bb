"""Load figures of the `traffictwin` CLI with many inputs per call (prints JSON).

    python -m benchmarks.cli_load [--pairs 200] [--frames 800] [--batch-size 8] [--risk-batch 16]

Builds its own inputs in a temp folder (no pipeline outputs needed): a fusion model folder with
params.yaml's ``fusion_model.architecture`` on params.yaml's grid and a DAVE-2 risk model folder
(the headline variant's inputs: RGB + SGM disparity + speed) with the camera / SGM / ORB settings
of ``risk_data`` in its ``domain`` metadata, both with random weights (time and memory do not
depend on the weights); ``--pairs`` random grid pairs listed in a CSV, and ``--frames`` textured
stereo pairs of the camera size. Then runs, each as one CLI process:

- ``traffictwin fuse --pairs LIST.csv`` (batched inference, one PNG preview per pair): wall time
  and max RSS;
- ``traffictwin risk FOLDER`` (frames streamed in batches): wall time and max RSS.

Targets: 200 pairs <= 15 s on the 2-core machine; 800 frames with max RSS <= 400 MB.
Wall times include the process start (imports) and, for ``risk``, ORB + SGM on every frame;
``cpu_s`` (user + system CPU seconds of the process) is given beside them because on a shared
machine the wall time mostly measures the other tenants.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def machine_info() -> dict:
    """The machine a CLI/pipeline benchmark ran on: CPUs, 1-min load average, platform, Python."""
    return {
        "cpus": os.cpu_count(),
        "load_avg_1m": round(os.getloadavg()[0], 2),
        "platform": platform.platform(),
        "python": platform.python_version(),
    }


def load_params(path: Path) -> dict:
    import yaml

    return yaml.safe_load(path.read_text())


def build_fusion_model(folder: Path, cfg: dict) -> dict:
    """A fusion model folder (random weights) with params.yaml's architecture and grid."""
    import torch

    from traffictwin.fusion.deeplab import DeepLabV3Plus
    from traffictwin.fusion.training import spec_from_cfg
    from traffictwin.model_format import model_checkpoint, save_model_checkpoint

    torch.manual_seed(0)
    spec = spec_from_cfg(cfg["fusion_model"]["architecture"])
    net = DeepLabV3Plus(spec).eval()
    g = cfg["grid"]
    grid = {"rows": int(g["rows"]), "cols": int(g["cols"]), "cell": float(g["cell"])}
    meta = {"cfg": "D", "grid": grid, "data_manifest_hash": "benchmark"}
    ck = model_checkpoint("fusion", spec.as_dict(), net.state_dict(), meta)
    folder.mkdir(parents=True, exist_ok=True)
    save_model_checkpoint(folder / "model.ckpt", ck)
    (folder / "model_meta.json").write_text(json.dumps(ck["traffictwin"], indent=2))
    return grid


def build_risk_model(folder: Path, cfg: dict) -> tuple[int, int]:
    """A DAVE-2 risk model folder (random weights, speed input) with the data's domain."""
    import torch

    from traffictwin.risk.dave2 import Dave2, Dave2Config
    from traffictwin.risk.model_io import save_risk_model

    rd = cfg["risk_data"]
    w, h = int(rd["camera"]["width"]), int(rd["camera"]["height"])
    torch.manual_seed(0)
    domain = {
        "camera": {"width": w, "height": h},
        "sgm": dict(rd["sgm"]),
        "orb": dict(rd["orb"]),
        "max_speed": float(rd["max_speed"]),
    }
    save_risk_model(Dave2(Dave2Config(use_speed=True)).eval(), folder, {"domain": domain})
    return w, h


def write_pairs(folder: Path, n: int, grid: dict) -> Path:
    """``n`` random map pairs (.npz) and their list ``pairs.csv``."""
    rng = np.random.default_rng(0)
    folder.mkdir(parents=True, exist_ok=True)
    rows = []
    for k in range(n):
        for side in ("a", "b"):
            d = rng.dirichlet([1.0, 1.0, 1.0], size=(grid["rows"], grid["cols"])).astype(np.float32)
            np.savez(
                folder / f"{k:04d}{side}.npz", m_free=d[..., 0], m_occ=d[..., 1], cell=grid["cell"]
            )
        rows.append([f"{k:04d}", f"{k:04d}a.npz", f"{k:04d}b.npz", 0, 0, 0, 2.0, -1.0, 0.05])
    lst = folder / "pairs.csv"
    with open(lst, "w", newline="") as fh:
        wr = csv.writer(fh)
        wr.writerow(["id", "map1", "map2", "x1", "y1", "yaw1", "x2", "y2", "yaw2"])
        wr.writerows(rows)
    return lst


def write_frames(folder: Path, n: int, w: int, h: int) -> Path:
    """``n`` textured rectified pairs ``<id>_left.png`` / ``<id>_right.png`` (6 px disparity)."""
    import cv2

    rng = np.random.default_rng(1)
    folder.mkdir(parents=True, exist_ok=True)
    for k in range(n):
        tex = cv2.resize(
            rng.integers(0, 256, size=(h // 4, (w + 16) // 4, 3), dtype=np.uint8),
            (w + 16, h),
            interpolation=cv2.INTER_NEAREST,
        )
        cv2.imwrite(str(folder / f"{k:05d}_left.png"), tex[:, :w])
        cv2.imwrite(str(folder / f"{k:05d}_right.png"), tex[:, 6 : w + 6])
    return folder


def cli_env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join((str(ROOT / "src"), str(ROOT), env.get("PYTHONPATH", "")))
    return env


# Peak RSS of the CLI process itself: VmHWM of /proc/self/status, read at exit. (getrusage's
# ru_maxrss would not do: Linux carries the pre-exec high-water mark over exec, so a child of this
# benchmark, which has torch loaded, would report at least this process's RSS.)
_WRAPPER = (
    "import atexit, runpy, sys\n"
    "def _hwm():\n"
    "    for ln in open('/proc/self/status'):\n"
    "        if ln.startswith('VmHWM'):\n"
    "            print('@@VmHWM_kB', ln.split()[1], file=sys.stderr)\n"
    "atexit.register(_hwm)\n"
    "sys.argv = ['traffictwin', *sys.argv[1:]]\n"
    "runpy.run_module('traffictwin.cli', run_name='__main__')\n"
)


def run_measured(args: list[str], cwd: Path) -> dict:
    """Run ``traffictwin ARGS`` in a fresh Python: wall time (s, process start included), CPU
    time (s, user + system) and the process's peak RSS (MB)."""
    t0 = time.perf_counter()
    p = subprocess.Popen(
        [sys.executable, "-c", _WRAPPER, *args],
        cwd=cwd,
        env=cli_env(),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    err = p.stderr.read().decode() if p.stderr else ""
    _, status, ru = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    p.returncode = os.waitstatus_to_exitcode(status)
    if p.returncode != 0:
        raise RuntimeError(f"traffictwin {' '.join(args)} failed: {err[-2000:]}")
    hwm = [ln.split()[1] for ln in err.splitlines() if ln.startswith("@@VmHWM_kB")]
    return {
        "wall_s": round(wall, 2),
        "cpu_s": round(ru.ru_utime + ru.ru_stime, 2),
        "max_rss_mb": round(int(hwm[-1]) / 1024, 1) if hwm else None,
    }


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pairs", type=int, default=200)
    ap.add_argument("--frames", type=int, default=800)
    ap.add_argument("--batch-size", type=int, default=8)
    ap.add_argument("--risk-batch", type=int, default=16)
    ap.add_argument("--params", default=str(ROOT / "params.yaml"))
    a = ap.parse_args(argv)
    cfg = load_params(Path(a.params))
    res: dict = {"machine": machine_info()}
    with tempfile.TemporaryDirectory(prefix="tt-cli-load-") as tmp:
        t = Path(tmp)
        grid = build_fusion_model(t / "fusion", cfg)
        w, h = build_risk_model(t / "risk", cfg)
        lst = write_pairs(t / "maps", a.pairs, grid)
        frames = write_frames(t / "frames", a.frames, w, h)
        fuse = run_measured(
            [
                "fuse",
                "--pairs",
                str(lst),
                "--model",
                str(t / "fusion"),
                "--batch-size",
                str(a.batch_size),
                "-o",
                str(t / "fused"),
            ],
            t,
        )
        risk = run_measured(
            [
                "risk",
                str(frames),
                "--model",
                str(t / "risk"),
                "--speed",
                "12",
                "--batch-size",
                str(a.risk_batch),
                "-o",
                str(t / "risk.csv"),
            ],
            t,
        )
        n_rows = sum(1 for _ in open(t / "risk.csv")) - 1
        n_out = len(list((t / "fused").glob("*.npz")))
    res["fuse_pairs"] = {
        "pairs": a.pairs,
        "grid": [grid["rows"], grid["cols"]],
        "batch_size": a.batch_size,
        **fuse,
        "per_pair_ms": round(1e3 * fuse["wall_s"] / a.pairs, 1),
        "outputs": n_out,
        "target_s": 15.0,
    }
    res["risk_folder"] = {
        "frames": a.frames,
        "image": [w, h],
        "batch_size": a.risk_batch,
        **risk,
        "per_frame_ms": round(1e3 * risk["wall_s"] / a.frames, 1),
        "rows": n_rows,
        "target_max_rss_mb": 400.0,
    }
    print(json.dumps(res, indent=2))
    return res


if __name__ == "__main__":
    main()
