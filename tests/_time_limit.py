"""A time limit for a block of a test (``SIGALRM``): a hang (a FIFO opened by mistake, a pool
that never ends, a lock never released) ends as a failure naming the limit instead of stopping
the suite. pytest-timeout is not a dependency; ``tests/conftest.py`` puts every test under
``tests/reliability/`` under :func:`time_limit` with :func:`limit_for` its markers."""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

#: seconds per test call, by marker (the first that applies); a test's own subprocesses carry
#: their own, shorter timeouts
LIMITS_S = {"slow": 3600.0, "integration": 900.0}
DEFAULT_LIMIT_S = 600.0


class TimeLimitExceeded(Exception):
    """A test (or block) ran past its time limit."""


def limit_for(markers: set[str]) -> float:
    """The limit in seconds of a test with ``markers`` (names)."""
    return next((s for m, s in LIMITS_S.items() if m in markers), DEFAULT_LIMIT_S)


@contextmanager
def time_limit(seconds: float, what: str = "the test") -> Iterator[None]:
    """Raise :class:`TimeLimitExceeded` in the block after ``seconds`` (a blocking system call,
    such as opening a FIFO, is interrupted). Off the main thread or without ``SIGALRM``: no
    limit (the block runs as it is)."""
    if (
        not hasattr(signal, "setitimer")
        or threading.current_thread() is not threading.main_thread()
    ):
        yield
        return

    def expired(signum, frame):  # noqa: ANN001, ARG001
        raise TimeLimitExceeded(f"{what} ran longer than its time limit of {seconds:g} s")

    previous = signal.signal(signal.SIGALRM, expired)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
