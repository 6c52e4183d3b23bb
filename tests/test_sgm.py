"""SGM wrapper and disparity metrics."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from traffictwin.sim.camera import StereoCamera
from traffictwin.sim.scene import Boxes, Cls
from traffictwin.stereo.metrics import (
    accuracy_table,
    disparity_errors,
    grouped_accuracy,
    per_frame_accuracy,
    summarise,
)
from traffictwin.stereo.sgm import (
    INVALID,
    SgmParams,
    compute_disparity,
    disparity_frames,
    make_matcher,
    valid_share,
)

BAD2_BOUND = 0.05  # stated bound: < 5 % of valid pixels off by > 2 px on a clean rendered pair


@pytest.fixture(scope="module")
def pair():
    cam = StereoCamera()
    boxes = Boxes(
        [[15, 0], [25, 3.5], [8, -3.5], [40, -10], [30, 12]],
        [[4.5, 1.8, 1.5], [4.5, 1.8, 1.5], [4.5, 1.8, 1.5], [20, 10, 12], [15, 8, 9]],
        [0, 0.1, 0, 0, 0.3],
        [Cls.CAR, Cls.CAR, Cls.CAR, Cls.BUILDING, Cls.BUILDING],
    )
    return cam.render_pair((0.0, 0.0, 0.0), boxes, rng=np.random.default_rng(0))


def test_sgm_on_rendered_pair_matches_gt(pair):
    d = compute_disparity(pair["left"], pair["right"], num_disparities=32, block_size=5)
    m = summarise(disparity_errors(d, pair["disp_gt"]))
    assert m["bad2"] < BAD2_BOUND
    assert m["density"] > 0.5
    assert m["epe"] < 1.0


def test_invalid_pixels_are_minus_one(pair):
    d = compute_disparity(pair["left"], pair["right"], num_disparities=32)
    assert d.dtype == np.float32
    # OpenCV cannot match the left border without the full search range: invalid, kept invalid
    assert np.all(d[:, :32] == INVALID)
    assert set(np.unique(d[d < 0])) == {INVALID}
    assert np.all(d[d >= 0] <= 32)


def test_penalties_follow_the_design():
    m = make_matcher(64, 5, channels=3)
    assert m.getP1() == 8 * 3 * 25 and m.getP2() == 32 * 3 * 25
    assert m.getDisp12MaxDiff() == 1 and m.getMode() == 1  # STEREO_SGBM_MODE_HH
    # speckle filter on by default: OpenCV's documented recipe (window 50-200 px, range 1-2 px)
    assert m.getSpeckleWindowSize() == 100 and m.getSpeckleRange() == 2
    with pytest.raises(ValueError, match="multiple of 16"):
        make_matcher(30)
    with pytest.raises(ValueError, match="odd"):
        make_matcher(32, 4)


def test_mismatched_sizes_and_dtypes_raise(pair):
    with pytest.raises(ValueError, match="differ in size"):
        compute_disparity(pair["left"], pair["right"][:, :-4])
    with pytest.raises(ValueError, match="uint8"):
        compute_disparity(pair["left"].astype(np.float32), pair["right"])


def test_metric_hand_case():
    gt = np.array([[10.0, 10.0, 10.0, 10.0, 0.0]], np.float32)
    est = np.array([[10.5, 13.0, 11.0, -1.0, 5.0]], np.float32)
    s = disparity_errors(est, gt)
    m = summarise(s)
    assert m["density"] == pytest.approx(3 / 4)
    assert m["bad2"] == pytest.approx(1 / 3)  # only the 3 px error
    assert m["d1"] == pytest.approx(0.0)  # 3 px is not > 3 px
    assert m["epe"] == pytest.approx((0.5 + 3.0 + 1.0) / 3)
    # sums over frames, then ratios: two copies of the frame give the same ratios
    two = pd.DataFrame(
        [{"shard": 0, "idx": k, "split": "test", "fault": "none", **s} for k in range(2)]
    )
    g = grouped_accuracy(two, ("train", "val", "test"), ("none", "delay", "vertical"))
    assert {k.split("/")[1]: v for k, v in g.items() if k.startswith("all/")} == pytest.approx(m)
    assert set(g) == {f"{p}/{k}" for p in ("all", "test", "fault_none") for k in m}
    with pytest.raises(ValueError, match="shape"):
        disparity_errors(est, gt[:, :3])


def test_disparity_frames_match_single_calls(pair):
    p = SgmParams(
        num_disparities=32,
        block_size=5,
        uniqueness_ratio=10,
        speckle_window=100,
        speckle_range=2,
        gray=False,
    )
    m = p.matcher()
    assert (m.getNumDisparities(), m.getBlockSize(), m.getP1()) == (32, 5, 8 * 3 * 25)
    left = np.stack([pair["left"], pair["left"]])
    right = np.stack([pair["right"], pair["right"]])
    disp, secs = disparity_frames(left, right, p)
    one = compute_disparity(pair["left"], pair["right"], num_disparities=32, block_size=5)
    assert disp.shape == (2, *one.shape) and disp.dtype == np.float32 and secs >= 0
    assert np.array_equal(disp[0], one) and np.array_equal(disp[1], one)
    gray = disparity_frames(left[:1], right[:1], SgmParams(**{**p.__dict__, "gray": True}))[0]
    assert np.array_equal(
        gray[0], compute_disparity(pair["left"], pair["right"], num_disparities=32, gray=True)
    )


def test_accuracy_table_and_per_frame_values():
    gt = np.array([[10.0, 10.0, 10.0, 10.0, 0.0]], np.float32)
    good = disparity_errors(gt.copy(), gt)
    bad = disparity_errors(np.array([[10.5, 13.0, 11.0, -1.0, 5.0]], np.float32), gt)
    frames = pd.DataFrame(
        {
            "frame_id": [0, 1, 2],
            "shard": [0, 0, 1],
            "idx": [0, 1, 0],
            "split": ["train", "train", "test"],
            "fault": ["none", "vertical", "none"],
        }
    )
    df = accuracy_table(frames, {1: [bad], 0: [good, bad]})
    assert list(df.frame_id) == [0, 1, 2] and df.n_valid.tolist() == [4.0, 3.0, 3.0]
    per = per_frame_accuracy(df)
    assert list(per.columns) == ["frame_id", "density", "bad2", "d1", "epe"]
    assert per.density.tolist() == pytest.approx([1.0, 0.75, 0.75])
    assert per.bad2.tolist() == pytest.approx([0.0, 1 / 3, 1 / 3])
    g = grouped_accuracy(df, ("train", "val", "test"), ("none", "delay", "vertical"))
    assert g["all/density"] == pytest.approx(10 / 12)  # 10 valid of 12 GT pixels
    assert g["fault_none/bad2"] == pytest.approx(1 / 7)  # frames 0 and 2: 1 bad of 7 valid
    assert g["fault_vertical/epe"] == pytest.approx(4.5 / 3)
    assert "val/density" not in g and "fault_delay/density" not in g


def test_speckle_filter_only_invalidates_and_lowers_bad2(pair):
    off = compute_disparity(pair["left"], pair["right"], num_disparities=32, speckle_window=0)
    on = compute_disparity(pair["left"], pair["right"], num_disparities=32)  # default: 100 px, 2 px
    kept = on >= 0
    assert not np.any(kept & (off < 0))  # nothing becomes valid
    assert np.array_equal(on[kept], off[kept])  # surviving values unchanged
    assert kept.sum() < (off >= 0).sum()  # some speckles removed on this pair
    s_on, s_off = (summarise(disparity_errors(d, pair["disp_gt"])) for d in (on, off))
    assert s_on["bad2"] <= s_off["bad2"]


def test_valid_share_hand_case():
    d = np.full((2, 8), INVALID, np.float32)
    d[:, 3:] = 4.0  # band = min_disparity 1 + num_disparities 2 = 3 columns never count
    d[0, 3] = INVALID
    d[1, 5:7] = INVALID  # 3 of the 10 matchable pixels invalid
    assert float(valid_share(d, 2, 1)) == pytest.approx(0.7)
    d[:, :3] = 0.0  # valid values inside the band do not count either
    assert float(valid_share(d, 2, 1)) == pytest.approx(0.7)
    both = valid_share(np.stack([d, np.zeros_like(d)]), 2, 1)
    assert both.shape == (2,) and both.tolist() == pytest.approx([0.7, 1.0])
    with pytest.raises(ValueError, match="unmatched band of 8"):
        valid_share(d, 8)
    with pytest.raises(ValueError, match="shape"):
        valid_share(d[0], 2)


def test_valid_share_of_a_rendered_pair(pair):
    d = compute_disparity(pair["left"], pair["right"], num_disparities=32)
    assert float(valid_share(d, 32)) == pytest.approx(float((d[:, 32:] >= 0).mean()))
    assert float(valid_share(d, 32)) > 0.8  # a clean pair
