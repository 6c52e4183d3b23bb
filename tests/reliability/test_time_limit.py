"""Every reliability test runs under a time limit: a blocking call (opening a FIFO that no one
writes) ends as a failure naming the limit, and the limit follows the test's markers."""

from __future__ import annotations

import os
import time

import pytest
from _time_limit import DEFAULT_LIMIT_S, TimeLimitExceeded, limit_for, time_limit


def test_a_blocking_open_of_a_fifo_ends_at_the_limit(tmp_path):
    fifo = tmp_path / "f"
    os.mkfifo(fifo)
    start = time.monotonic()
    with pytest.raises(TimeLimitExceeded, match="x ran longer than its time limit of 0.5 s"):
        with time_limit(0.5, what="x"):
            fifo.open("rb")  # blocks until a writer opens it: none will
    assert time.monotonic() - start < 5


def test_the_limit_is_off_after_the_block(tmp_path):
    with time_limit(0.2):
        pass
    time.sleep(0.4)  # no late alarm


def test_limits_follow_the_markers():
    assert limit_for(set()) == DEFAULT_LIMIT_S
    assert limit_for({"integration"}) < limit_for({"slow"}) == limit_for({"slow", "integration"})


def test_this_test_runs_under_a_limit():
    """The hook in tests/conftest.py: SIGALRM is armed while a reliability test runs."""
    import signal

    remaining, _ = signal.getitimer(signal.ITIMER_REAL)
    assert 0 < remaining <= DEFAULT_LIMIT_S
