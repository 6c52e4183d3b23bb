"""The one nested-key helper (traffictwin.nested.lookup) on hand-made dicts."""

from __future__ import annotations

from traffictwin.nested import ABSENT, lookup


def test_dotted_keys_and_flat_keys() -> None:
    data = {"A": {"net": {"test/kld": 1.5}}, "test/mse": 2.0, "x": {"y": {"z": 4}}}
    assert lookup(data, "A.net.test/kld") == 1.5
    assert lookup(data, "test/mse") == 2.0  # a flat key with '/'
    assert lookup(data, "x.y.z") == 4
    assert lookup(data, "x.y") == {"z": 4}
    assert lookup(data, "") is data


def test_segments_that_contain_dots_take_the_longest_prefix() -> None:
    data = {"models": {"v": {"at_1.5s": {"roc_auc": 0.9}, "at_1": {"5s": {"roc_auc": 0.1}}}}}
    assert lookup(data, "models.v.at_1.5s.roc_auc") == 0.9
    seeds = {"seed_sd": {"at_1.5s.roc_auc": 0.04}}  # a flat key holding the whole dotted path
    assert lookup(seeds, "seed_sd.at_1.5s.roc_auc") == 0.04
    # the longest prefix that leads somewhere wins; a dead end falls back to a shorter one
    assert lookup({"a.b": {"c": 1}, "a": {"b": {"d": 2}}}, "a.b.d") == 2


def test_list_levels_take_indices() -> None:
    data = {"candidates": [{"x": 1}, {"x": 2}], "grid": [3, 4]}
    assert lookup(data, "candidates.1.x") == 2
    assert lookup(data, "grid.0") == 3
    assert lookup(data, "grid.5") is None and lookup(data, "grid.first", "-") == "-"


def test_absent_gives_the_default_and_null_is_present() -> None:
    data = {"a": {"b": None}, "n": 0}
    assert lookup(data, "a.c") is None and lookup(data, "a.c", "<missing>") == "<missing>"
    assert lookup(data, "a.b", ABSENT) is None  # JSON null: present, returned as None
    assert lookup(data, "a.c", ABSENT) is ABSENT
    assert lookup(data, "n.deeper", ABSENT) is ABSENT  # below a scalar
    assert lookup(None, "a") is None and lookup([], "0", 7) == 7
