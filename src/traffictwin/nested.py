"""Looking up a value in nested JSON data (dicts and lists) by a dotted key.

The one home of nested-key lookup: the report's tables, the risk findings, the README's results
blocks and the dataset manifests' checks all read nested metrics or parameters through
:func:`lookup`. It knows no file layout; it depends on nothing in the package.
"""

from __future__ import annotations

from typing import Any

__all__ = ["ABSENT", "lookup"]

#: a default that tells an absent key from a JSON ``null`` (``lookup(d, k, ABSENT) is ABSENT``)
ABSENT = object()


def lookup(data: Any, key: str, default: Any = None) -> Any:
    """Nested lookup of ``key`` = segments joined by '.', where a segment may contain '.' or '/'.

    At each level the longest prefix of the remaining key that is a dict key wins, so
    ``"test.A.dnn.kld_fo_mean"``, ``"models.v.at_1.5s.accuracy"`` and a flat
    ``{"test/mse": …}`` all resolve; at a list level the segment is an index
    (``"candidates.0.x"``). ``default`` when the key is absent (a JSON ``null`` is present and
    returned as None).
    """
    if key == "":
        return data
    if isinstance(data, list):
        head, _, rest = key.partition(".")
        if head.isdigit() and int(head) < len(data):
            return lookup(data[int(head)], rest, default)
        return default
    if not isinstance(data, dict):
        return default
    if key in data:
        return data[key]
    parts = key.split(".")
    for i in range(len(parts) - 1, 0, -1):
        head = ".".join(parts[:i])
        if head in data:
            found = lookup(data[head], ".".join(parts[i:]), ABSENT)
            if found is not ABSENT:
                return found
    return default
