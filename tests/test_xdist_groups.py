"""``xdist_group`` marks hold under pytest 9: a grouped test's node id carries its group, by which
``--dist loadgroup`` sends the group to one worker (``tests/conftest.py``: ``_join_xdist_group``),
and the recorded durations keep the plain node id."""

from __future__ import annotations

import pytest
from conftest import plain_nodeid


def test_plain_nodeid_drops_only_a_group_suffix() -> None:
    assert plain_nodeid("tests/a.py::t@g") == "tests/a.py::t"
    assert plain_nodeid("tests/a.py::t[x@y]") == "tests/a.py::t[x@y]"  # an @ in a parameter
    assert plain_nodeid("tests/a.py::t[x@y]@g") == "tests/a.py::t[x@y]"
    assert plain_nodeid("tests/a.py::t") == "tests/a.py::t"


@pytest.mark.xdist_group("probe")
def test_a_grouped_test_carries_its_group_under_loadgroup(request: pytest.FixtureRequest) -> None:
    """Under `make test` (``-n auto --dist loadgroup``) the id ends with ``@probe``; in one
    process (``-n 0``) there is no group and no suffix."""
    if getattr(request.config.option, "loadgroup", False):
        assert request.node.nodeid.endswith(
            "::test_a_grouped_test_carries_its_group_under_loadgroup@probe"
        )
    else:
        assert "@" not in request.node.nodeid
