"""The one JSON cleaner (traffictwin.io.jsonio.json_clean): hand cases and the exact JSON text."""

import json
from collections import OrderedDict

import numpy as np

from traffictwin.io.atomic import write_json_atomic
from traffictwin.io.jsonio import json_clean


def test_non_finite_floats_become_null():
    assert json_clean({"a": [float("inf"), 1.0], "b": float("nan")}) == {
        "a": [None, 1.0],
        "b": None,
    }
    assert json_clean([np.float32("nan"), np.float64("-inf"), -float("inf")]) == [None, None, None]


def test_numpy_scalars_become_python_with_the_same_value():
    out = json_clean({"f32": np.float32(0.1), "f64": np.float64(2.5), "i": np.int64(7)})
    assert type(out["f32"]) is float and out["f32"] == float(np.float32(0.1))
    assert type(out["f64"]) is float and out["f64"] == 2.5
    assert type(out["i"]) is int and out["i"] == 7


def test_containers_keys_and_other_values():
    src = OrderedDict([("z", (1, 2.0)), ("a", {"n": None, "t": True, "s": "x"})])
    out = json_clean(src)
    assert type(out) is dict and list(out) == ["z", "a"]  # order kept
    assert out == {"z": [1, 2.0], "a": {"n": None, "t": True, "s": "x"}}
    assert type(out["a"]["t"]) is bool
    assert json_clean({3: 1.0, np.str_("k"): 2.0}) == {"3": 1.0, "k": 2.0}
    arr = np.arange(3)
    assert json_clean(arr) is arr  # arrays are left to the writer (tolist)


def test_the_json_text_is_what_the_writers_wrote(tmp_path):
    # the three former cleaners' callers write through write_json_atomic / json.dumps
    m = {"b": np.float32(0.5), "a": [np.float64(1 / 3), float("nan")], "c": np.int32(4)}
    write_json_atomic(tmp_path / "m.json", json_clean(m))
    assert (tmp_path / "m.json").read_text() == (
        '{\n  "a": [\n    0.3333333333333333,\n    null\n  ],\n  "b": 0.5,\n  "c": 4\n}\n'
    )
    assert json.dumps(json_clean({"thw_s": float("inf"), "ok": 1.25}), indent=2) == (
        '{\n  "thw_s": null,\n  "ok": 1.25\n}'
    )
