"""traffictwin.processes.map_indexed: results by task index in any finishing order, each worker set
up once, Ctrl-C left to the parent."""

from __future__ import annotations

import os
import signal
import time

from traffictwin.processes import map_indexed

_STATE: dict[str, int] = {}


def _init(offset: int) -> None:
    _STATE["offset"] = offset


def _task(t: tuple[int, int]) -> tuple[int, tuple[int, int, bool]]:
    i, x = t
    time.sleep(0.05 * (3 - i % 3))  # later tasks finish first
    ignored = signal.getsignal(signal.SIGINT) == signal.SIG_IGN
    return i, (x * x + _STATE["offset"], os.getpid(), ignored)


def test_results_come_back_in_task_order_from_set_up_workers() -> None:
    tasks = [(i, x) for i, x in enumerate([3, 1, 4, 1, 5, 9])]
    out = map_indexed(_task, iter(tasks), 6, 2, method="spawn", initializer=_init, initargs=(10,))
    assert [r[0] for r in out] == [19, 11, 26, 11, 35, 91]  # x² + 10, in task order
    assert all(r[2] for r in out)  # every worker ignores SIGINT
    assert len({r[1] for r in out}) == 2 and os.getpid() not in {r[1] for r in out}
