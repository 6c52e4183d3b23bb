"""Fusion network throughput on this machine (prints JSON).

    python -m benchmarks.fusion_model [--threads N] [--steps 4] [--rows 256 --cols 176] [--skip-resnet50]
        [--device cuda] [--precision bf16-mixed] [--r50-batch 80]

For the default profile's network (conf/fusion_model/resnet18.yaml) and the paper's ResNet-50
DeepLabV3+ (resnet50.yaml), both at the given grid:

- ``train_samples_per_s``: forward + evidential loss + backward + Adam step, with the paper's
  flip/rotation augmentation, at the profile's batch size (ResNet-50: ``--r50-batch``, default 8,
  on a CPU), median step time over ``--steps`` steps after one warm-up step;
- ``infer_ms_per_pair``: eval-mode forward at batch 1 and per pair at batch 8 (median of 3);
- ``param_count``;
- ``default_profile_estimate_s``: epochs x samples/epoch / samples/s for the default sizes;
- ``fwd_gflop_per_pair``: forward FLOPs (torch's FlopCounterMode);
- ``paper_profile_estimate_h_on_this_cpu``: the paper profile (8,000 training pairs, ~200 epochs)
  at the measured ResNet-50 CPU rate; ``..._gpu_at_100_tflops``: the same from FLOPs (training
  ~3x forward) at an assumed sustained 100 TFLOP/s — an estimate, not a GPU measurement.

``--device cuda`` measures on the first CUDA device instead (timings after
``torch.cuda.synchronize``; ``peak_gpu_mem_gib``); ``--precision bf16-mixed`` runs the forward
under bf16 autocast with the loss in float32, as the ``gpu`` trainer group does. There the
ResNet-50's ``paper_profile_h_on_this_device`` is measured: 200 epochs x 8,000 pairs at the
measured training rate (data loading and validation not included).

Figures depend on the machine's load; the JSON reports the CPU, thread count and load average.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path
from typing import Any

import torch
import yaml

from traffictwin.config import typed
from traffictwin.fusion.deeplab import (
    DeepLabV3Plus,
    channels_last_supported,
    count_parameters,
)
from traffictwin.fusion.losses import evidential_loss
from traffictwin.fusion.model_config import FusionModelConfig
from traffictwin.fusion.training_data import augment
from traffictwin.threads import pin_threads

ROOT = Path(__file__).resolve().parents[1]


def _cpu_name() -> str:
    try:
        with open("/proc/cpuinfo") as fh:
            for ln in fh:
                if ln.startswith("model name"):
                    return ln.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _load_group(name: str) -> tuple[FusionModelConfig, Path]:
    path = ROOT / "conf" / "fusion_model" / f"{name}.yaml"
    return typed(yaml.safe_load(path.read_text()), FusionModelConfig, key="", source=path), path


def _clock(device: torch.device) -> float:
    """Wall time (s) after the device's queued work has finished."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return time.perf_counter()


def measure(
    loaded: tuple[FusionModelConfig, Path],
    rows: int,
    cols: int,
    batch: int,
    steps: int,
    device: torch.device | None = None,
    bf16: bool = False,
) -> dict[str, Any]:
    """Training and inference speed of the network described by a ``fusion_model`` group, on
    ``device`` (default CPU); ``bf16``: forward under bf16 autocast, the loss in float32."""
    device = device or torch.device("cpu")
    torch.manual_seed(0)
    group, path = loaded
    net = DeepLabV3Plus(group.deeplab_spec(path, key=""))
    cl = group.train.channels_last and channels_last_supported(net)
    fmt = torch.channels_last if cl else torch.contiguous_format
    net = net.to(device=device, memory_format=fmt)
    opt = torch.optim.Adam(net.parameters(), lr=group.optim.lr)
    g = torch.Generator().manual_seed(0)
    x = (torch.rand(batch, 4, rows, cols, generator=g) / 2).to(device, memory_format=fmt)
    y = (torch.rand(batch, 2, rows, cols, generator=g) / 2).to(device)
    autocast = torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16)
    net.train()
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    times = []
    for i in range(steps + 1):
        t = _clock(device)
        xa, ya = augment(x, y, flip=True, max_rotation_deg=20.0, generator=g)
        with autocast:
            e = net(xa.contiguous(memory_format=fmt))
        loss = evidential_loss(e.float(), ya, 3.0)
        opt.zero_grad()
        loss.backward()
        opt.step()
        if i > 0:
            times.append(_clock(device) - t)
    step_s = statistics.median(times)
    net.eval()
    out: dict[str, Any] = {
        "param_count": count_parameters(net),
        "train_batch": batch,
        "channels_last": cl,
        "train_step_s": round(step_s, 4),
        "train_samples_per_s": round(batch / step_s, 3),
    }
    if device.type == "cuda":
        out["peak_gpu_mem_gib"] = round(torch.cuda.max_memory_allocated(device) / 2**30, 2)
    from torch.utils.flop_counter import FlopCounterMode

    with FlopCounterMode(display=False) as fc, torch.no_grad():
        net(x[:1])
    out["fwd_gflop_per_pair"] = round(fc.get_total_flops() / 1e9, 3)
    with torch.no_grad(), autocast:
        for b in (1, 8):
            xb = x[:1].expand(b, -1, -1, -1).contiguous(memory_format=fmt)
            net(xb)
            ts = []
            for _ in range(3):
                t = _clock(device)
                net(xb)
                ts.append(_clock(device) - t)
            out[f"infer_ms_per_pair_batch{b}"] = round(1e3 * statistics.median(ts) / b, 2)
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description="fusion network throughput (JSON)")
    ap.add_argument("--rows", type=int, default=256)
    ap.add_argument("--cols", type=int, default=176)
    ap.add_argument("--steps", type=int, default=4)
    ap.add_argument(
        "--threads", type=int, default=0, help="torch intra-op threads (0: torch default)"
    )
    ap.add_argument("--r50-batch", type=int, default=8)
    ap.add_argument("--skip-resnet50", action="store_true")
    ap.add_argument("--device", default="cpu", help="cpu | cuda | cuda:<i>")
    ap.add_argument("--precision", default="32-true", choices=("32-true", "bf16-mixed"))
    args = ap.parse_args(argv)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        ap.error(f"--device {args.device}: this machine has no CUDA device")
    bf16 = args.precision == "bf16-mixed"
    if args.threads > 0:
        pin_threads(args.threads)
    default = _load_group("resnet18")
    res: dict[str, Any] = {
        "machine": {
            "cpu": _cpu_name(),
            "cores": os.cpu_count(),
            "torch_threads": torch.get_num_threads(),
            "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
            "torch": torch.__version__,
            "loadavg_1min": round(os.getloadavg()[0], 2),
            "device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
            "precision": args.precision,
        },
        "grid": [args.rows, args.cols],
    }
    d = measure(
        default, args.rows, args.cols, default[0].train.batch_size, args.steps, device, bf16
    )
    train = default[0].train
    n_epoch = train.train_samples_per_epoch or 1600
    d["default_profile_estimate_s"] = round(
        train.max_epochs * n_epoch / d["train_samples_per_s"], 1
    )
    res["default_" + default[0].name] = d
    if not args.skip_resnet50:
        r50 = _load_group("resnet50")
        m = measure(
            r50, args.rows, args.cols, args.r50_batch, max(2, args.steps // 2), device, bf16
        )
        # paper: 10,000 pairs, 80:10:10 -> 8,000 training pairs per epoch, ~200 epochs
        where = "device" if device.type == "cuda" else "cpu"
        m[f"paper_profile_estimate_h_on_this_{where}"] = round(
            200 * 8000 / m["train_samples_per_s"] / 3600, 2
        )
        # GPU: not measured here; training ~ 3x forward FLOPs, at an assumed sustained 100 TFLOP/s (bf16, H100-class)
        m["paper_profile_estimate_h_gpu_at_100_tflops"] = round(
            3 * m["fwd_gflop_per_pair"] * 1e9 * 200 * 8000 / 1e14 / 3600, 2
        )
        res["paper_resnet50"] = m
    print(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
