"""JSON-safe values: the one place that turns NaN/inf into ``null`` (strict JSON, DVC metrics).

:func:`json_clean` is used for every metrics file, run record and CLI summary; writing is
:func:`traffictwin.io.atomic.write_json_atomic`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

__all__ = ["json_clean"]


def json_clean(obj: Any) -> Any:
    """A strict-JSON copy of ``obj``, recursively.

    Non-finite floats (NaN, ±inf; Python or numpy) → ``None``; finite numpy floats → ``float``
    (the same value, so the same digits in JSON), numpy integers → ``int``; mappings → ``dict``
    with ``str`` keys (what JSON makes of them; order kept); lists and tuples → ``list``.
    Anything else (str, int, bool, None, arrays, ...) is returned as it is.
    """
    if isinstance(obj, Mapping):
        return {str(k): json_clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_clean(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj
