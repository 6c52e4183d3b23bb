"""The tail breakdown of the critical-object range error, by hand."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks import stereo_tail as T


def test_edge_bands_mark_the_pixels_near_a_disparity_jump() -> None:
    gt = np.array([[[2, 2, 2, 2, 4, 4, 4, 4]]], float)  # a 2 px jump between columns 3 and 4
    bands = T.edge_bands(gt)
    assert np.flatnonzero(bands[1][0, 0]).tolist() == [3, 4]
    assert np.flatnonzero(bands[2][0, 0]).tolist() == [2, 3, 4, 5]
    assert not T.edge_bands(gt + np.linspace(0, 0.4, 8))[1][0, 0, :3].any()  # a slope is no edge


def test_tail_breakdown_hand_case() -> None:
    gt = np.array([[[2, 2, 2, 2, 4, 4, 4, 4]]], float)
    est = np.array([[[2, 2, 2, 2.5, 4, 4, 4, 4.4]]], float)
    res = T.tail_breakdown(gt, {"x": est}, np.ones_like(gt, bool))
    # relative errors |gt / d - 1|: 0.2 at column 3 (an edge pixel), 1/11 at column 7, else 0
    assert res["pixels"] == 8 and res["edge1px_share"] == 0.25 and res["edge2px_share"] == 0.5
    x = res["x"]
    assert x["median"] == 0.0
    # empirical p90: the smallest value with >= 90 % at or below it (8 values: the 8th)
    assert x["p90"] == pytest.approx(0.2)
    assert x["p90_without_edge1px"] == pytest.approx(1 / 11)  # 0 x5, 1/11: the 6th
    assert x["p90_without_edge2px"] == pytest.approx(1 / 11)  # 0, 0, 0, 1/11: the 4th
    assert x["edge1px_share_of_worst10"] == 1.0  # the one value >= p90 is the edge pixel's
    assert x["abs_err_px_p90"] == pytest.approx(0.5)  # sorted 0 x6, 0.4, 0.5
    assert x["over_1px_share"] == 0.0
    zero = T.tail_breakdown(gt, {"x": np.where(gt > 3, 0.0, gt)}, np.ones_like(gt, bool))
    assert zero["x"]["p90"] == np.inf  # 0 px: an infinite range, an infinite error
