"""Stage entry-point helpers: the traceback switch and bugs that must keep their traceback, and
``map_shards``. That every bad-input failure type ends in one line and exit 2 is
``tests/reliability/test_stage_errors.py``."""

from __future__ import annotations

import pytest

from pipelines._common import run_stage
from traffictwin.config import ConfigError
from traffictwin.io.shards import DatasetError


def test_traceback_on_request_and_other_errors_propagate(monkeypatch) -> None:
    monkeypatch.setenv("TRAFFICTWIN_TRACEBACK", "1")
    with pytest.raises(ConfigError):
        run_stage(lambda: (_ for _ in ()).throw(ConfigError("bad")), "s")
    monkeypatch.delenv("TRAFFICTWIN_TRACEBACK")
    with pytest.raises(TypeError):  # a bug, not bad input: the traceback stays
        run_stage(lambda: len(3), "s")
    run_stage(lambda: None, "s")  # success returns normally


def _square(i: int) -> tuple[int, int]:
    from pipelines._common import WORKER_STATE

    return i, i * i + WORKER_STATE["offset"]


@pytest.mark.parametrize("workers", [1, 2])
def test_map_shards_gives_every_result_with_the_state(workers: int) -> None:
    from pipelines._common import map_shards

    got = dict(map_shards(_square, range(5), workers=workers, state={"offset": 10}, desc="unit"))
    assert got == {i: i * i + 10 for i in range(5)}
    assert [
        i
        for i, _ in map_shards(
            _square, range(5), workers=workers, state={"offset": 0}, desc="unit", ordered=True
        )
    ] == list(range(5))


def _boom(i: int) -> int:
    if i == 1:
        raise DatasetError(f"shard {i}: corrupt")
    return i


@pytest.mark.parametrize("workers", [1, 2])
def test_map_shards_propagates_worker_errors(workers: int) -> None:
    from pipelines._common import map_shards

    with pytest.raises(DatasetError, match="shard 1: corrupt"):
        list(map_shards(_boom, [0, 1, 2], workers=workers, state={}, desc="unit"))
