"""benchmarks/fusion_model.py: the measurement on a tiny grid (CPU, float32 and bf16 autocast) and
its device argument's check."""

from __future__ import annotations

import math

import pytest
import torch

from benchmarks import fusion_model as B


@pytest.mark.parametrize("bf16", [False, True])
def test_measure_reports_positive_rates_on_a_tiny_grid(bf16: bool) -> None:
    group = B._load_group("resnet18")
    out = B.measure(group, 32, 32, batch=2, steps=1, device=torch.device("cpu"), bf16=bf16)
    assert out["train_batch"] == 2
    assert out["param_count"] > 100_000
    for key in ("train_step_s", "train_samples_per_s", "fwd_gflop_per_pair"):
        assert math.isfinite(out[key]) and out[key] > 0, key
    assert out["train_samples_per_s"] == pytest.approx(2 / out["train_step_s"], rel=0.01)
    assert set(out) >= {"infer_ms_per_pair_batch1", "infer_ms_per_pair_batch8"}
    assert "peak_gpu_mem_gib" not in out  # only measured on a CUDA device


def test_cuda_device_without_cuda_is_one_clear_error(monkeypatch, capsys) -> None:
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(SystemExit) as exc:
        B.main(["--device", "cuda", "--skip-resnet50"])
    assert exc.value.code == 2
    assert "--device cuda: this machine has no CUDA device" in capsys.readouterr().err
