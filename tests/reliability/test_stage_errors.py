"""Every stage error is one line naming the parameter or file, with exit 2, and nothing is written
before the parameters are checked."""

from __future__ import annotations

import logging
import shutil
import signal
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from pipelines._common import error_line, run_stage
from traffictwin.config import ConfigError, typed
from traffictwin.io.shards import DatasetError

# ---------------------------------------------------------------------------------------------
# error_line and run_stage


def test_error_line_is_class_and_message_on_one_line() -> None:
    assert error_line(ValueError("high - low < 0")) == "ValueError: high - low < 0"
    assert error_line(KeyError("trainer")) == "KeyError: 'trainer'"
    assert error_line(RuntimeError()) == "RuntimeError"
    multi = RuntimeError("OpenCV(5.0.0) x.cpp:510: error: (-2)\n> too small\n\n>   width is 0\n")
    assert (
        error_line(multi)
        == "RuntimeError: OpenCV(5.0.0) x.cpp:510: error: (-2) | > too small | >   width is 0"
    )


def _cv2_error() -> BaseException:
    import cv2

    try:
        cv2.StereoSGBM.create(numDisparities=64, blockSize=5).compute(
            np.zeros((8, 8), np.uint8), np.zeros((8, 8), np.uint8)
        )
    except cv2.error as exc:
        return exc
    raise AssertionError("OpenCV accepted an 8 px wide pair")


def _errors() -> list[BaseException]:
    from lightning.fabric.utilities.exceptions import MisconfigurationException
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    from traffictwin.trainer import TrainingDiverged

    try:
        OmegaConf.create({"a": 1}, flags={"struct": True}).b  # noqa: B018
    except OmegaConfBaseException as exc:
        omega = exc
    return [
        ConfigError("params.yaml: 'x' must be >= 1, got -3"),
        DatasetError("data/x: manifest missing"),
        KeyError("risk_model"),
        FileNotFoundError(2, "No such file or directory", "data/orb/orb.csv"),
        FloatingPointError("overflow"),
        TrainingDiverged("train_fusion@A: training diverged at epoch 0, step 1"),
        MisconfigurationException("`MPSAccelerator` can not run on your system"),
        omega,
        _cv2_error(),
    ]


@pytest.mark.parametrize("exc", _errors(), ids=lambda e: type(e).__name__)
def test_stage_failures_are_one_line_and_exit_2(exc: BaseException, capsys, monkeypatch) -> None:
    monkeypatch.delenv("TRAFFICTWIN_TRACEBACK", raising=False)

    def main() -> None:
        raise exc

    with pytest.raises(SystemExit) as info:
        run_stage(main, "unit_stage")
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert err == f"unit_stage: error: {error_line(exc)}\n" and err.count("\n") == 1
    monkeypatch.setenv("TRAFFICTWIN_TRACEBACK", "1")
    with pytest.raises(type(exc)):
        run_stage(main, "unit_stage")


def test_an_interrupted_run_exits_128_plus_the_signal(capsys, monkeypatch) -> None:
    from traffictwin.mlops.tracking import RunInterrupted

    monkeypatch.delenv("TRAFFICTWIN_TRACEBACK", raising=False)

    def main() -> None:
        raise RunInterrupted(signal.SIGTERM)

    with pytest.raises(SystemExit) as info:
        run_stage(main, "train_fusion")
    assert info.value.code == 128 + signal.SIGTERM
    assert capsys.readouterr().err == "train_fusion: interrupted: received SIGTERM\n"


# ---------------------------------------------------------------------------------------------
# parameter checks of the library (hand cases)


def test_bounded_settings_must_be_finite() -> None:
    from traffictwin.fusion.training import OptimConfig

    node = {"lr": 0.01, "weight_decay": 0.0, "lr_factor": 0.5, "lr_patience": 3}
    assert typed(node, OptimConfig, key="fusion_model.optim").lr == 0.01
    for bad in (float("inf"), float("nan")):
        with pytest.raises(ConfigError, match=r"'fusion_model.optim.lr' must be a finite number"):
            typed({**node, "lr": bad}, OptimConfig, key="fusion_model.optim")


def test_top_speed_below_what_the_situations_draw_is_refused() -> None:
    from traffictwin.sim.driving import MIN_TOP_SPEED, DrivingConfig

    assert MIN_TOP_SPEED == 12.0  # approach_slow draws the subject's speed in [12, max_speed]
    DrivingConfig(max_speed=12.0)
    with pytest.raises(ValueError, match=r"max_speed must be >= 12.0 m/s"):
        DrivingConfig(max_speed=11.9)


def test_sgm_needs_the_search_range_plus_half_a_block_inside_the_image() -> None:
    from traffictwin.stereo.sgm import SgmParams, check_image_width, compute_disparity

    check_image_width(19, 16, 5)  # 19 > 0 + 16 + 5 // 2 = 18
    with pytest.raises(ValueError, match=r"need images wider than .* = 18 px .*got 18 px"):
        check_image_width(18, 16, 5)
    p = SgmParams(
        num_disparities=512,
        block_size=5,
        uniqueness_ratio=10,
        speckle_window=0,
        speckle_range=2,
        gray=False,
    )
    with pytest.raises(ValueError, match=r"params: num_disparities=512 and block_size=5 .* 514 px"):
        p.check_width(320, what="params")
    img = np.zeros((16, 16, 3), np.uint8)  # what OpenCV refuses with a cv2.error
    with pytest.raises(ValueError, match=r"stereo pair 16x16: .*got 16 px"):
        compute_disparity(img, img, num_disparities=16, block_size=5)


@pytest.mark.parametrize(
    "text, match",
    [
        ('frame_id,outlier\n0,False\n1,"open\n', r"orb.csv: not a readable CSV table"),
        ("", r"orb.csv: not a readable CSV table \(EmptyDataError"),
        ("frame_id,flag\n0,False\n", r"orb.csv: column 'outlier' missing"),
        (
            "frame_id,outlier\n0,False\nx,True\n",
            r"column 'frame_id' must hold integers, row 3 has 'x'",
        ),
        ("frame_id,outlier\n0,False\n0,True\n", r"column 'frame_id' repeats frame 0"),
        ("frame_id,outlier\n0,False\n1,maybe\n", r"column 'outlier' must hold booleans .*'maybe'"),
    ],
)
def test_corrupt_orb_table_names_file_and_column(tmp_path: Path, text: str, match: str) -> None:
    from traffictwin.risk.training import read_orb_table

    p = tmp_path / "orb.csv"
    p.write_text(text)
    with pytest.raises(DatasetError, match=match):
        read_orb_table(p)


def test_valid_orb_table_reads_unchanged(tmp_path: Path) -> None:
    from traffictwin.risk.training import read_orb_table

    p = tmp_path / "orb.csv"
    p.write_text("frame_id,n,outlier\n3,5,False\n1,7,True\n")
    got = read_orb_table(p)
    pd.testing.assert_frame_equal(got, pd.read_csv(p))


# ---------------------------------------------------------------------------------------------
# the stages themselves: exit 2, one stderr line naming the parameter, outputs untouched


@pytest.fixture(scope="module")
def ci_repo(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from conftest import copy_repo, run

    repo = copy_repo(tmp_path_factory.mktemp("stage_errors") / "repo")
    run([sys.executable, "-m", "pipelines.compose_params", "profile=ci"], repo)
    return repo


def _set(params: dict, dotted: str, value) -> None:
    node = params
    *head, last = dotted.split(".")
    for k in head:
        node = node[k]
    node[last] = value


SENTINEL = b"an output of an earlier run\n"
BAD_PARAMS = [
    (
        "generate_risk",
        [],
        {"risk_data.max_speed": 3.0},
        "'risk_data.max_speed' must be >= 12.0",
        "data/risk",
    ),
    (
        "disparity",
        [],
        {"risk_data.sgm.num_disparities": 512},
        "'risk_data.sgm': num_disparities=512",
        "data/disparity",
    ),
    (
        "train_risk",
        ["--variant", "headline"],
        {"risk_data.sgm.num_disparities": 64},
        "'risk_data.sgm.num_disparities'=64 exceeds 'risk_model.disp_scale'",
        "models/risk/headline",
    ),
    (
        "train_fusion",
        [],
        {"fusion_model.optim.lr": float("inf")},
        "'fusion_model.optim.lr' must be a finite number",
        "models/fusion/network",
    ),
    (
        "train_fusion",
        [],
        {"trainer.accelerator": "mps"},
        "'trainer' (accelerator='mps'",
        "models/fusion/network",
    ),
    (
        "train_fusion",
        [],
        {"fusion_model.optim.bogus": 1},
        "'fusion_model.optim.bogus'",
        "models/fusion/network",
    ),
]
BAD_PARAMS_IDS = ["max_speed", "sgm_width", "disp_scale", "lr_inf", "accelerator", "unknown_key"]


@contextmanager
def _bad_params(repo: Path, overrides: dict, output: str) -> Iterator[Path]:
    """``repo``'s params.yaml with ``overrides`` and a file of an earlier run in ``output``
    (yielded) for the block; the good params.yaml afterwards."""
    pfile = repo / "params.yaml"
    good = pfile.read_text()
    params = yaml.safe_load(good)
    for k, v in overrides.items():
        _set(params, k, v)
    out = repo / output
    out.mkdir(parents=True, exist_ok=True)
    (out / "earlier.bin").write_bytes(SENTINEL)
    try:
        pfile.write_text(yaml.safe_dump(params, sort_keys=False))
        yield out
    finally:
        pfile.write_text(good)
        shutil.rmtree(out)


def _untouched(out: Path) -> None:
    assert [p.name for p in out.iterdir()] == ["earlier.bin"]
    assert (out / "earlier.bin").read_bytes() == SENTINEL


@pytest.mark.slow
@pytest.mark.parametrize("stage, args, overrides, named, output", BAD_PARAMS, ids=BAD_PARAMS_IDS)
def test_bad_params_end_in_one_line_before_outputs_are_touched(
    ci_repo: Path,
    stage: str,
    args: list[str],
    overrides: dict,
    named: str,
    output: str,
    caplog: pytest.LogCaptureFixture,
) -> None:
    """In this process (the stage's ``main`` under ``run_stage``); the process boundary is
    checked once below."""
    from conftest import stage_in_process

    caplog.set_level(logging.INFO)  # what `python -m` would print: setup_logging's level
    with _bad_params(ci_repo, overrides, output) as out:
        code, err = stage_in_process(ci_repo, stage, args)
        _untouched(out)
    assert code == 2, err[-3000:]
    lines = err.splitlines()
    assert len(lines) == 1, err[-3000:]
    assert lines[0].startswith(f"{stage}: error: ") and named in lines[0]
    # nothing logged before the error line
    assert caplog.records == [], [(r.name, r.getMessage()) for r in caplog.records]


@pytest.mark.slow
def test_a_stage_process_with_bad_params_exits_2_with_one_stderr_line(ci_repo: Path) -> None:
    """The exit-code contract across the process boundary (``python -m pipelines.<stage>``)."""
    from conftest import run

    stage, args, overrides, named, output = BAD_PARAMS[0]
    with _bad_params(ci_repo, overrides, output) as out:
        proc = run([sys.executable, "-m", f"pipelines.{stage}", *args], ci_repo, check=False)
        _untouched(out)
    assert proc.returncode == 2, proc.stderr[-3000:]
    lines = proc.stderr.splitlines()
    assert len(lines) == 1, proc.stderr[-3000:]
    assert lines[0].startswith(f"{stage}: error: ") and named in lines[0]


def test_device_settings_must_name_a_device_this_machine_has() -> None:
    import torch

    from traffictwin.trainer import check_device

    check_device("cpu", "params.yaml", "evaluation.fusion.device")
    with pytest.raises(ConfigError, match=r"'evaluation.fusion.device' is not a torch device"):
        check_device("gpu0", "params.yaml", "evaluation.fusion.device")
    with pytest.raises(ConfigError, match=r"must be cpu or cuda\[:i\], got 'meta'"):
        check_device("meta", "params.yaml", "evaluation.fusion.device")
    n = torch.cuda.device_count() if torch.cuda.is_available() else 0
    with pytest.raises(ConfigError, match=rf"is 'cuda:{n}' but this machine has {n} CUDA device"):
        check_device(f"cuda:{n}", "params.yaml", "evaluation.fusion.device")


def test_lidar_ranges_are_named_by_their_dotted_keys() -> None:
    """``fusion_data.lidar.min_range`` above max_range failed with ``LidarSpec: need
    max_range > min_range`` and no parameter named."""
    from conftest import committed

    from traffictwin.fusion.config import fusion_data_config

    cfg = yaml.safe_load(committed("params.yaml"))
    fusion_data_config(cfg)  # the committed values pass
    cfg["fusion_data"]["lidar"]["min_range"] = 90.0
    with pytest.raises(
        ValueError, match=r"'fusion_data\.lidar\.min_range' \(90\.0 m\) must be below"
    ):
        fusion_data_config(cfg)
