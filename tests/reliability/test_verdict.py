"""The risk verdict answers to the stereo pair check (a pair that fails it, such as uniform
images or swapped cameras, has verdict "unknown" with the reason and exit status 3, never
"uncritical"); ``fuse`` says when map 2 misses map 1's grid; poses too large to subtract are
refused in terms of the options; the speed bound is printed with every digit."""

from __future__ import annotations

import csv
import json
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
from _cli_models import (
    CELL,
    fuse_args,
    masses,
    save_fusion_model,
    save_map,
    save_risk,
    textured_pair,
    write_pair,
)

from traffictwin import api, cli
from traffictwin.cli.risk import EXIT_UNKNOWN
from traffictwin.stereo.orb import check_pair

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE_LEFT, EXAMPLE_RIGHT = (
    ROOT / "examples/risk/000_left.png",
    ROOT / "examples/risk/000_right.png",
)


@pytest.fixture(scope="module")
def risk_dir(tmp_path_factory) -> Path:
    return save_risk(
        tmp_path_factory.mktemp("r") / "m",
        {"label": "risk", "domain": {"speed_range": [0.0, 25.0]}},
        use_speed=True,
    )


@pytest.fixture(scope="module")
def fusion_dir(tmp_path_factory) -> Path:
    return save_fusion_model(tmp_path_factory.mktemp("f") / "m")


def _listing(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def _err_line(capsys, *needles: str) -> tuple[str, str]:
    cap = capsys.readouterr()
    err = cap.err.strip().splitlines()
    assert len(err) == 1, err
    for n in needles:
        assert n in err[0], err[0]
    return err[0], cap.out


# ------------------------------------------------------------------ the check


def test_check_passes_good_pairs_and_flags_swapped_and_uniform_ones():
    left, right = textured_pair()
    good = check_pair(left, right)
    assert not good.outlier and not good.swapped and good.reason == ""
    assert good.median_dx == pytest.approx(6.0)
    swapped = check_pair(right, left)
    assert swapped.outlier and swapped.swapped
    assert swapped.median_dx == pytest.approx(-6.0)
    assert "left and right images swapped" in swapped.reason
    # the |dx| / |dy| rule alone passes the swapped pair: only the sign catches it
    assert swapped.mean_dx >= 1.0 and swapped.mean_dy <= 5.0
    for value in (0, 128, 255):
        flat = np.full_like(left, value)
        res = check_pair(flat, flat)
        assert res.outlier and "uniform or textureless" in res.reason
    ex = [cv2.imread(str(p)) for p in (EXAMPLE_LEFT, EXAMPLE_RIGHT)]
    assert not check_pair(*ex).outlier  # the shipped example, a simulator pair
    assert check_pair(ex[1], ex[0]).swapped


# ------------------------------------------------------------------ the API's verdict


def test_api_gives_no_verdict_for_an_unreliable_pair(risk_dir):
    rm = api.load_risk(risk_dir)
    left, right = textured_pair()
    black = np.zeros_like(left)
    frames = [
        api.Frame("ok", left, right),
        api.Frame("sw", right, left),
        api.Frame("bk", black, black),
    ]
    rows = {r["id"]: r for r in api.assess_risk(rm, frames, speed=8.0)}
    assert rows["ok"]["verdict"] in ("critical", "uncritical")
    assert isinstance(rows["ok"]["critical"], bool) and rows["ok"]["verdict_reason"] == ""
    for fid, why in (("sw", "swapped"), ("bk", "uniform or textureless")):
        r = rows[fid]
        assert r["orb_verdict"] == "unreliable pair"
        assert r["verdict"] == api.UNKNOWN == "unknown" and r["critical"] is None
        assert (
            r["verdict_reason"].startswith("the stereo pair failed its check")
            and why in r["verdict_reason"]
        )


def test_risk_verdict_of_an_unreliable_pair_is_unknown():
    v = api.risk_verdict(0.5, 8.0, unreliable="median dx -6 px: swapped")
    assert v["verdict"] == "unknown" and v["critical"] is None and "swapped" in v["verdict_reason"]
    assert api.risk_verdict(0.5, 8.0)["verdict"] == "critical"


# ------------------------------------------------------------------ the CLI's verdict and exit status


def test_cli_swapped_pair_exits_3_with_verdict_unknown(tmp_path, risk_dir, capsys):
    out = tmp_path / "o.json"
    base = ["--speed", "8.725", "--model", str(risk_dir)]
    assert cli.main(["risk", str(EXAMPLE_LEFT), str(EXAMPLE_RIGHT), *base]) == 0
    good = json.loads(capsys.readouterr().out)
    assert good["verdict"] in ("critical", "uncritical") and good["orb_verdict"] == "ok"
    before = _listing(ROOT / "examples/risk")
    rc = cli.main(["risk", str(EXAMPLE_RIGHT), str(EXAMPLE_LEFT), *base, "-o", str(out)])
    assert rc == EXIT_UNKNOWN == 3
    _, stdout = _err_line(
        capsys, "traffictwin risk: warning: no verdict for", "000_right.png", "images swapped"
    )
    res = json.loads(stdout)
    assert res["verdict"] == "unknown" and res["critical"] is None
    assert res["orb_verdict"] == "unreliable pair" and "swapped" in res["orb_reason"]
    assert json.loads(out.read_text()) == res  # the output is written all the same
    assert _listing(ROOT / "examples/risk") == before


def test_cli_black_images_exit_3_never_uncritical(tmp_path, risk_dir, capsys):
    black = np.zeros((160, 320, 3), np.uint8)
    lp, rp = write_pair(tmp_path, "k", black, black)
    rc = cli.main(["risk", str(lp), str(rp), "--speed", "8", "--model", str(risk_dir)])
    assert rc == 3
    _, stdout = _err_line(capsys, "no verdict for", "uniform or textureless")
    res = json.loads(stdout)
    assert res["verdict"] == "unknown" and res["verdict"] != "uncritical"


def test_cli_folder_marks_the_unreliable_rows_and_exits_3(tmp_path, risk_dir, capsys):
    left, right = textured_pair()
    folder = tmp_path / "pairs"
    write_pair(folder, "a", left, right)
    write_pair(folder, "b", right, left)  # swapped
    black = np.zeros_like(left)
    write_pair(folder, "c", black, black)
    out = tmp_path / "rows.csv"
    argv = ["risk", str(folder), "--speed", "8", "--model", str(risk_dir), "-o", str(out)]
    assert cli.main(argv) == 3
    line, stdout = _err_line(capsys, "no verdict for", "b_left.png", "(and 1 more pair(s))")
    assert "2 without a verdict" in stdout
    rows = {r["id"]: r for r in csv.DictReader(out.open())}
    assert rows["a"]["verdict"] in ("critical", "uncritical") and rows["a"]["verdict_reason"] == ""
    assert rows["b"]["verdict"] == rows["c"]["verdict"] == "unknown"
    assert rows["b"]["critical"] == rows["c"]["critical"] == ""
    folder_only = tmp_path / "good"
    write_pair(folder_only, "a", left, right)
    assert cli.main(["risk", str(folder_only), "--speed", "8", "--model", str(risk_dir)]) == 0


def test_speed_just_above_the_range_prints_every_digit(tmp_path, risk_dir, capsys):
    lp, rp = write_pair(tmp_path, "f", *textured_pair())
    argv = ["risk", str(lp), str(rp), "--speed", "25.000001", "--model", str(risk_dir)]
    assert cli.main(argv) == 1
    _err_line(capsys, "--speed: 25.000001 m/s is outside the model's training range [0, 25] m/s")


# ------------------------------------------------------------------ fuse: no overlap, huge poses


def _maps(tmp_path: Path) -> tuple[Path, Path]:
    return (
        save_map(tmp_path / "a.npz", *masses(1), cell=np.float64(CELL)),
        save_map(tmp_path / "b.npz", *masses(2), cell=np.float64(CELL)),
    )


def test_fuse_warns_when_map2_misses_map1s_grid(tmp_path, fusion_dir, capsys):
    m1, m2 = _maps(tmp_path)
    argv = fuse_args(m1, m2, fusion_dir, tmp_path / "o")
    assert cli.main(argv) == 0
    assert capsys.readouterr().err == ""  # overlapping poses: no warning
    argv = [a if a != "4.0,1.0,-0.05" else "1e6,0,0" for a in argv]
    argv[argv.index("-o") + 1] = str(tmp_path / "far")
    assert cli.main(argv) == 0
    line, stdout = _err_line(
        capsys, "traffictwin fuse: warning:", "b.npz does not overlap", "the output is map 1 alone"
    )
    assert json.loads(stdout)["overlap"] is False
    with np.load(tmp_path / "far.npz") as z:
        assert z["m_free"].shape == masses(1)[0].shape


def test_fuse_huge_poses_name_the_options_not_internals(tmp_path, fusion_dir, capsys):
    m1, m2 = _maps(tmp_path)
    before = _listing(tmp_path)
    argv = [str(m1), str(m2), "--pose1=1e308,0,0", "--pose2=-1e308,0,0"]
    argv = ["fuse", *argv, "--model", str(fusion_dir), "-o", str(tmp_path / "o")]
    assert cli.main(argv) == 1
    line, _ = _err_line(capsys, "--pose1, --pose2: map 2's pose relative to map 1 is not finite")
    assert "warp_masses" not in line
    assert _listing(tmp_path) == before  # nothing written


def test_fuse_pose_1e308_is_no_overlap_not_a_full_one(fusion_dir):
    fm = api.load_fusion(fusion_dir)
    m1, m2 = np.stack(masses(1)), np.stack(masses(2))
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        (far,) = api.fuse(fm, [api.FusePair(m1, m2, [0, 0, 0], [1e308, 0, 0], CELL, "p")])
        (near,) = api.fuse(fm, [api.FusePair(m1, m2, [0, 0, 0], [2.0, 0, 0], CELL, "q")])
    assert not far.overlap and float(far.m2_prealigned.sum()) == 0.0  # was a full warp: garbage
    assert near.overlap and float(near.m2_prealigned.sum()) > 0
    msgs = [str(x.message) for x in w if issubclass(x.category, api.ApiWarning)]
    assert len(msgs) == 1 and msgs[0].startswith("pair 'p': map 2 does not overlap map 1's grid")


def test_pair_list_nan_cell_is_blamed_on_the_list_not_on_cell_option(tmp_path, fusion_dir, capsys):
    m1, m2 = _maps(tmp_path)
    lst = tmp_path / "pairs.csv"
    lst.write_text(f"map1,map2,cell\n{m1.name},{m2.name},nan\n")
    argv = ["fuse", "--pairs", str(lst), "--model", str(fusion_dir), "-o", str(tmp_path / "out")]
    assert cli.main(argv) == 1
    line, _ = _err_line(capsys, "pairs.csv line 2: column cell = 'nan' must be a positive number")
    assert "--cell" not in line
    assert not (tmp_path / "out").exists()


def test_orb_sweep_at_the_configured_threshold_counts_swapped_pairs():
    import pandas as pd

    from traffictwin.stereo.orb import orb_metrics

    df = pd.DataFrame(
        {
            "n_reliable": [50, 50],
            "mean_dx": [6.0, 6.0],
            "mean_dy": [0.1, 0.1],
            "swapped": [False, True],
            "outlier": [False, True],
            "fault": ["none", "none"],
            "split": ["test", "test"],
            "speed": [8.0, 8.0],
        }
    )
    m = orb_metrics(df, ["test"], ["none"], min_reliable=8, min_dx=1.0)
    assert m["sweep/max_dy_5_false_alarm_rate"] == m["all/false_alarm_rate"] == 0.5
