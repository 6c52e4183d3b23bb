"""The object mask (traffictwin.stereo.metrics, used by benchmarks/stereo_resolution.py and the
stereo_learned stage) and a tiny end-to-end run of the benchmark."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from benchmarks import stereo_resolution as B
from traffictwin.sim.camera import StereoCamera
from traffictwin.stereo.metrics import object_mask


def test_object_mask_separates_objects_from_road_and_sky() -> None:
    cam = StereoCamera(width=64, height=32)  # cy = 15.5, fy = fx
    depth = np.full((32, 64), np.inf)
    rows = np.arange(16, 32)
    ground = cam.mount_height * cam.fy / (rows - cam.cy)
    depth[16:, :] = ground[:, None]  # road surface everywhere below the horizon
    depth[20, 10] = 0.5 * ground[4]  # a box in front of the road
    depth[5, 3] = 30.0  # a building above the horizon
    depth[25, 40] = 0.99 * ground[9]  # road within 3 %: still road
    mask = object_mask(depth, cam.cy, cam.fy, cam.mount_height)
    assert mask[20, 10] and mask[5, 3]
    assert not mask[25, 40] and not mask[0, 0]  # road, sky
    assert mask.sum() == 2


def test_tiny_study_writes_json_and_figure(tmp_path: Path) -> None:
    out_json, out_fig = tmp_path / "m.json", tmp_path / "f.png"
    argv = ["--frames", "4", "--widths", "64", "128", "--n-boot", "50"]
    m = B.main(argv + ["--out-json", str(out_json), "--out-fig", str(out_fig)])
    data = json.loads(out_json.read_text())
    assert data == json.loads(json.dumps(m)) and data["study/frames"] == 4
    assert data["w64/num_disparities"] == 16 and data["w128/num_disparities"] == 16
    assert data["w128/height"] == 64 and data["w64/sgm_ms_median"] > 0
    # the GT disparity at a distance doubles with the width (same field of view)
    assert data["w128/gt_disparity_px_at_12m"] == 2 * data["w64/gt_disparity_px_at_12m"]
    assert "diff_w128_minus_w64/crit_all_relerr_median" in data
    assert out_fig.stat().st_size > 1000
