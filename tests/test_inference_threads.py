"""pipelines._inference: the evaluation stages' torch thread count comes from params.yaml."""

from __future__ import annotations

import pytest
import torch

from pipelines._inference import THREADS_KEY, pin_torch_threads
from traffictwin.config import ConfigError


@pytest.fixture
def restore_threads():
    n = torch.get_num_threads()
    yield
    torch.set_num_threads(n)


@pytest.mark.parametrize("n", [1, 3])
def test_pin_sets_torch_threads_and_returns_them(n: int, restore_threads) -> None:
    assert pin_torch_threads({"evaluation": {"num_threads": n}}) == n
    assert torch.get_num_threads() == n


@pytest.mark.parametrize(
    "evaluation, expected",
    [
        ({"num_threads": 0}, ">= 1"),
        ({"num_threads": True}, "must be int"),
        ({"num_threads": "2"}, "must be int"),
        ({}, "missing"),
    ],
)
def test_bad_thread_count_names_the_key(evaluation: dict, expected: str, restore_threads) -> None:
    before = torch.get_num_threads()
    with pytest.raises(ConfigError, match=THREADS_KEY) as err:
        pin_torch_threads({"evaluation": evaluation})
    assert expected in str(err.value)
    assert torch.get_num_threads() == before  # nothing set on a bad value
