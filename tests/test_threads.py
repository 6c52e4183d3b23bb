"""traffictwin.threads: the one place that pins torch's CPU threads and OpenMP's wait policy."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

from traffictwin.threads import passive_omp_wait, pin_threads


@pytest.fixture
def restore_threads():
    n = torch.get_num_threads()
    yield n
    torch.set_num_threads(n)


@pytest.mark.parametrize("n", [1, 2])
def test_pin_sets_and_returns_the_count(n: int, restore_threads) -> None:
    assert pin_threads(n) == n and torch.get_num_threads() == n


@pytest.mark.parametrize("n", [None, 0])
def test_none_or_zero_keeps_torchs_count(n: int | None, restore_threads) -> None:
    torch.set_num_threads(1)
    assert pin_threads(n) == 1 and torch.get_num_threads() == 1


def test_negative_is_refused(restore_threads) -> None:
    with pytest.raises(ValueError, match=">= 0"):
        pin_threads(-1)
    assert torch.get_num_threads() == restore_threads


def test_passive_wait_is_a_default_only(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
    passive_omp_wait()
    import os

    assert os.environ["OMP_WAIT_POLICY"] == "PASSIVE"
    monkeypatch.setenv("OMP_WAIT_POLICY", "ACTIVE")
    passive_omp_wait()
    assert os.environ["OMP_WAIT_POLICY"] == "ACTIVE"  # an explicit setting wins


def test_importing_it_does_not_load_torch() -> None:
    code = "import sys, traffictwin.threads; assert 'torch' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)
