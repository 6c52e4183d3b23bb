"""Independent tasks in a pool of worker processes, their results in task order.

Library code's one pool: the classical registrations (``fusion.registration_batches``) and the
twin's sequences (``twin.evaluation``). The workers start from a fork server or are spawned (a fork
of a process with torch / OpenCV / logging threads could inherit a held lock and deadlock) and
ignore Ctrl-C, which the parent alone handles by ending the pool (no traceback per worker).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

__all__ = ["map_indexed"]


def _worker_init(initializer: Callable[..., None], initargs: tuple[Any, ...]) -> None:
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's: it ends the pool
    initializer(*initargs)


def map_indexed(
    task: Callable[[Any], tuple[int, Any]],
    tasks: Iterable[Any],
    n: int,
    workers: int,
    *,
    method: str,
    initializer: Callable[..., None],
    initargs: tuple[Any, ...] = (),
    chunksize: int = 1,
) -> list[Any]:
    """``[result_0, ..., result_{n-1}]`` of the ``n`` ``tasks``, each run as ``task(t) -> (i,
    result_i)`` in ``min(workers, n)`` processes of start method ``method`` (``"spawn"`` or
    ``"forkserver"``), each set up once by ``initializer(*initargs)``; results are placed by
    their index, so the list is the same whatever order they finish in. ``task`` and
    ``initializer`` must be module-level functions (they are pickled)."""
    import multiprocessing as mp

    out: list[Any] = [None] * n
    ctx = mp.get_context(method)
    init = (initializer, tuple(initargs))
    with ctx.Pool(min(workers, n), initializer=_worker_init, initargs=init) as pool:
        for i, result in pool.imap_unordered(task, tasks, chunksize=chunksize):
            out[i] = result
    return out
