"""Figures of the risk data stages, checked by what they plot (images, chosen frames, titles)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest

from traffictwin.grid import GridSpec
from traffictwin.io.shards import Dataset, DatasetWriter
from traffictwin.risk import data_figures
from traffictwin.risk.dataset import RiskDataSpec
from traffictwin.risk.metric import RiskConfig
from traffictwin.sim.camera import StereoCamera
from traffictwin.sim.driving import DrivingConfig
from traffictwin.stereo.orb import OrbParams

ORB = OrbParams(500, 12, 4, 19, 40.0, 50, 8, "mean", 1.0, 5.0)


@pytest.fixture
def figs(monkeypatch: pytest.MonkeyPatch) -> dict:
    """The figures data_figures saves, by file name, instead of files."""
    out: dict = {}
    monkeypatch.setattr(
        data_figures, "save_figure", lambda fig, path, **_: out.__setitem__(Path(path).name, fig)
    )
    return out


def _data(tmp: Path) -> tuple[Dataset, Dataset, pd.DataFrame]:
    rng = np.random.default_rng(0)
    rw = DatasetWriter(tmp / "risk", "risk", {}, 0)
    dw = DatasetWriter(tmp / "disparity", "disparity", {}, 0)
    faults = ["delay", "none", "none", "vertical"]
    speeds = [10.0, 2.0, 8.0, 9.0]  # frame 1 is too slow for the stereo example: frame 2 is shown
    rows = []
    for s in range(2):
        left = rng.integers(0, 255, (2, 48, 96, 3), dtype=np.uint8)
        left = np.stack([cv2.GaussianBlur(x, (3, 3), 0) for x in left])
        right = np.roll(left, -4, axis=2)
        gt = rng.uniform(1, 20, (2, 48, 96)).astype(np.float32)
        rw.add_shard(s, {"left": left, "right": right, "disp_gt": gt}, split="train")
        dw.add_shard(s, {"disp_sgm": gt - 0.5}, split="train")
        for k in range(2):
            f = 2 * s + k
            rows.append(
                dict(
                    frame_id=f,
                    shard=s,
                    idx=k,
                    split="train",
                    fault=faults[f],
                    speed=speeds[f],
                    template=f"tpl{f}",
                    situation="follow_close",
                )
            )
    frames = pd.DataFrame(rows)
    rw.add_table("frames.csv", frames)
    rw.finalize()
    dw.finalize()
    return Dataset(tmp / "risk", kind="risk"), Dataset(tmp / "disparity", kind="disparity"), frames


def test_stereo_example_shows_first_clean_moving_frame(tmp_path: Path, figs: dict) -> None:
    ds, dd, _ = _data(tmp_path)
    data_figures.stereo_example_figure(ds, dd, tmp_path / "stereo.png")
    fig = figs["stereo.png"]
    assert "frame 2 (tpl2, follow_close), v = 8.0 m/s" in fig._suptitle.get_text()
    ax = fig.axes
    assert [a.get_title() for a in ax][:2] == ["left image", "right image"]
    left = ds.load_shard(1)["left"][0]
    assert np.array_equal(ax[0].images[0].get_array(), cv2.cvtColor(left, cv2.COLOR_BGR2RGB))
    assert ax[3].get_title() == "SGM disparity (black: invalid)"
    # disparities in px on one scale (0 .. the GT's 99th percentile) with a colour bar each
    gt, sgm = ds.load_shard(1)["disp_gt"][0], dd.load_shard(1)["disp_sgm"][0]
    vmax = float(np.percentile(gt[gt > 0], 99))
    for a, d in ((ax[2], gt), (ax[3], sgm)):
        img = a.images[0]
        np.testing.assert_array_equal(img.get_array().filled(np.nan), d)
        assert img.get_clim() == (0.0, vmax) and img.colorbar.ax.get_ylabel() == "disparity (px)"
    assert len(ax) == 6  # 4 panels + 2 colour bars


def test_stereo_figure_masks_sky_and_invalid_disparity(figs: dict) -> None:
    img = np.zeros((4, 6, 3), np.uint8)
    gt = np.full((4, 6), 5.0, np.float32)
    gt[0] = 0.0  # sky: no surface, disparity 0
    sgm = gt.copy()
    sgm[1, :3] = -1.0  # OpenCV's invalid disparity
    sgm[0] = 0.0  # SGM 0 px: a valid (far) match
    data_figures.stereo_figure(img, img, gt, sgm, "s.png")
    ax = figs["s.png"].axes
    gt_mask, sgm_mask = ax[2].images[0].get_array().mask, ax[3].images[0].get_array().mask
    assert gt_mask[0].all() and not gt_mask[1:].any()
    assert sgm_mask[1, :3].all() and sgm_mask.sum() == 3
    assert tuple(ax[2].images[0].get_cmap().get_bad()[:3]) == (0.0, 0.0, 0.0)  # masked = black


def test_orb_example_shows_first_flagged_faulty_pair(tmp_path: Path, figs: dict) -> None:
    ds, _, frames = _data(tmp_path)
    table = frames[["frame_id", "fault"]].assign(
        n_matches=60,
        n_reliable=40,
        mean_dx=[4.0, 0.5, 4.0, 4.0],
        mean_dy=[0.2, 0.1, 0.3, 9.0],
        outlier=[False, True, False, True],
    )
    data_figures.orb_example_figure(ds, table, ORB, tmp_path / "orb.png")
    ax = figs["orb.png"].axes[0]
    assert ax.get_title().startswith(
        "frame 3: fault 'vertical', mean |dx| 4.00 px, mean |dy| 9.00 px"
    )
    sh = ds.load_shard(1)
    both = cv2.cvtColor(np.concatenate([sh["left"][1], sh["right"][1]], 1), cv2.COLOR_BGR2RGB)
    assert np.array_equal(ax.images[0].get_array(), both)
    assert len(ax.lines) > 0  # the best matches are drawn
    # no flagged faulty pair: the first flagged pair
    data_figures.orb_example_figure(
        ds, table.assign(outlier=[False, True, False, False]), ORB, tmp_path / "orb.png"
    )
    assert figs["orb.png"].axes[0].get_title().startswith("frame 1: fault 'none'")


def test_risk_metric_figure_plots_the_chosen_frame(tmp_path: Path, figs: dict) -> None:
    spec = RiskDataSpec(
        DrivingConfig(frames=3, warmup=1.0, situations=(("follow_close", 1.0),)),
        StereoCamera(width=96, height=48),
        GridSpec(128, 96, 0.64),
        RiskConfig(subject_length=4.8, subject_width=1.9),
        1.5,  # critical THW (s)
    )
    info = data_figures.risk_metric_figure(3, spec, tmp_path / "rm.png", max_sequences=4)
    cam, grid = figs["rm.png"].axes
    assert grid.get_xlabel() == "y (m, + = left)" and grid.get_ylabel() == "x (m, forward)"
    assert grid.get_title().startswith(f"THW {info['thw']:.2f} s")
    assert f"risk {info['risk']:.3f}" in grid.get_title()
    assert cam.get_title().startswith(f"{info['template']} / {info['situation']}")
    assert grid.images[0].get_array().shape == (128, 96, 3)
