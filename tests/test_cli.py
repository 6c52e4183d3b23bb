"""`traffictwin` CLI: round trips on generated data and clear errors that write nothing."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from _cli_models import (
    CELL,
    POSE1,
    POSE2,
    H,
    W,
    fuse_args,
    masses,
    save_fusion_model,
    save_map,
    save_risk,
    textured_pair,
)
from _registry_models import log_linear

from traffictwin import cli
from traffictwin.evidential.warp import warp_masses
from traffictwin.fusion.model_io import load_fusion_model, predict_masses
from traffictwin.geometry import relative_pose
from traffictwin.grid import GridSpec
from traffictwin.mlops import registry as reg
from traffictwin.risk.dave2 import Dave2, Dave2Config
from traffictwin.risk.model_io import load_risk_model, save_risk_model
from traffictwin.stereo.orb import check_pair
from traffictwin.stereo.sgm import compute_disparity
from traffictwin.trainer import log_model

_masses, _save_map = masses, save_map


@pytest.fixture(scope="module")
def fusion_dir(tmp_path_factory) -> Path:
    """A tiny fusion network saved in the checkpoint format of traffictwin.fusion.model_io."""
    return save_fusion_model(tmp_path_factory.mktemp("fusion_model"))


@pytest.fixture(scope="module")
def risk_dir(tmp_path_factory) -> Path:
    return save_risk(tmp_path_factory.mktemp("risk_model"), {"label": "risk_thw_paper"})


@pytest.fixture(scope="module")
def stereo_pair() -> tuple[np.ndarray, np.ndarray]:
    """A textured rectified pair: the right image is the left shifted by 6 px (disparity 6)."""
    return textured_pair()


def _files(folder: Path) -> set[str]:
    return {p.name for p in folder.rglob("*")}


# ------------------------------------------------------------------ fuse


def test_fuse_round_trip_equals_library(tmp_path, fusion_dir, capsys):
    mf1, mo1 = _masses(1)
    mf2, mo2 = _masses(2)
    p1 = _save_map(tmp_path / "a.npz", mf1, mo1, cell=np.float64(CELL))
    p2 = _save_map(tmp_path / "b.npz", mf2, mo2)
    rc = cli.main(fuse_args(p1, p2, fusion_dir, str(tmp_path / "out")))
    assert rc == 0
    summary = json.loads(capsys.readouterr().out)
    out = np.load(tmp_path / "out.npz")
    assert (tmp_path / "out.png").exists() and cv2.imread(str(tmp_path / "out.png")) is not None
    # the same through the library
    grid = GridSpec(H, W, CELL)
    rel = relative_pose(np.array([1.0, 2.0, 0.1]), np.array([4.0, 1.0, -0.05]))
    m2w = warp_masses(np.stack([mf2, mo2]), rel, grid)
    x = np.concatenate([np.stack([mf1, mo1]), m2w])[None]
    m, u = predict_masses(load_fusion_model(fusion_dir), x)
    np.testing.assert_allclose(out["m_free"], m[0, 0], atol=1e-6)
    np.testing.assert_allclose(out["m_occ"], m[0, 1], atol=1e-6)
    np.testing.assert_allclose(out["u"], u[0], atol=1e-6)
    assert out["m_free"].dtype == np.float32 and out["m_free"].shape == (H, W)
    np.testing.assert_allclose(out["m_free"] + out["m_occ"] + out["u"], 1.0, atol=1e-5)
    np.testing.assert_allclose(out["rel_pose"], rel)
    assert summary["grid"] == [H, W] and summary["cell_m"] == CELL


def test_fuse_with_registry_alias_matches_path(
    tmp_path, fusion_dir, mlflow_uri, monkeypatch, capsys
):
    import mlflow

    monkeypatch.chdir(tmp_path)
    cl = reg.client(mlflow_uri)
    net = load_fusion_model(fusion_dir)
    ckpt = torch.load(fusion_dir / "model.ckpt", weights_only=True)
    mlflow.set_experiment("fusion")
    with mlflow.start_run(run_name="fusion-D") as run:
        log_model(ckpt, ckpt["traffictwin"], net, np.zeros((1, 4, H, W), np.float32))
    mv = reg.ensure_version(cl, "traffictwin-fusion", run.info.run_id)
    cl.set_registered_model_alias("traffictwin-fusion", "champion", mv.version)
    p1 = _save_map(tmp_path / "a.npz", *_masses(4))
    p2 = _save_map(tmp_path / "b.npz", *_masses(5))
    common = ["fuse", str(p1), str(p2), "--pose1", POSE1, "--pose2", POSE2]
    # one network per task: the bare alias is traffictwin-fusion's, no configuration to name
    assert cli.main([*common, "--model", "champion", "-o", str(tmp_path / "reg")]) == 0
    assert (
        cli.main(
            [*common, "--model", str(fusion_dir), "--cell", str(CELL), "-o", str(tmp_path / "path")]
        )
        == 0
    )
    a, b = np.load(tmp_path / "reg.npz"), np.load(tmp_path / "path.npz")
    np.testing.assert_allclose(a["m_occ"], b["m_occ"], atol=1e-6)
    capsys.readouterr()
    # a missing alias names the model and the alias; nothing is written
    before = _files(tmp_path)
    assert cli.main([*common, "--model", "challenger", "-o", str(tmp_path / "x")]) == 1
    err = capsys.readouterr().err
    assert "traffictwin-fusion" in err and "challenger" in err
    assert _files(tmp_path) == before


def _bad_map_cases(tmp: Path) -> dict[str, tuple[Path, str]]:
    mf, mo = _masses(7)
    nan = mo.copy()
    nan[3, 4] = np.nan
    over = mo.copy()
    over[0, 0] = 0.9
    over_f = mf.copy()
    over_f[0, 0] = 0.9
    np.savez(tmp / "mk.npz", free=mf, m_occ=mo)
    (tmp / "junk.npz").write_bytes(b"not a zip")
    return {
        "shape3d": (_save_map(tmp / "s3.npz", mf[None], mo[None]), "2-D"),
        "shape_mismatch": (_save_map(tmp / "sm.npz", mf, mo[:, :-16]), "differ in shape"),
        "nan": (_save_map(tmp / "nan.npz", mf, nan), "NaN"),
        "outside_simplex": (_save_map(tmp / "ov.npz", over_f, over), "outside the simplex"),
        "negative": (_save_map(tmp / "neg.npz", mf - 0.5, mo), "outside the simplex"),
        "missing_key": (tmp / "mk.npz", "['m_free'] missing"),
        "int_dtype": (
            _save_map(tmp / "int.npz", (mf > 2).astype(np.int32), (mo > 2).astype(np.int32)),
            "float",
        ),
        "not_npz": (tmp / "junk.npz", "not a readable .npz"),
        "size_vs_map1": (_save_map(tmp / "small.npz", *_masses(8, 16, 16)), "differs from"),
    }


@pytest.mark.parametrize(
    "case",
    [
        "shape3d",
        "shape_mismatch",
        "nan",
        "outside_simplex",
        "negative",
        "missing_key",
        "int_dtype",
        "not_npz",
        "size_vs_map1",
        "not_divisible",
        "bad_pose",
        "missing_file",
    ],
)
def test_fuse_bad_input_errors_and_writes_nothing(tmp_path, fusion_dir, case, capsys):
    inp = tmp_path / "in"
    inp.mkdir()
    good = _save_map(inp / "good.npz", *_masses(9))
    cases = _bad_map_cases(inp)
    pose2, map2, want = POSE2, good, None
    if case == "bad_pose":
        pose2, want = "1,2", "--pose2"
    elif case == "missing_file":
        map2, want = inp / "nope.npz", "not found"
    elif case == "not_divisible":
        good = _save_map(inp / "g20.npz", *_masses(10, 20, 20))
        map2 = _save_map(inp / "h20.npz", *_masses(11, 20, 20))
        want = "divisible by 16"
    else:
        map2, want = cases[case]
    out = tmp_path / "out"
    out.mkdir()
    rc = cli.main(
        [
            "fuse",
            str(good),
            str(map2),
            "--pose1",
            POSE1,
            "--pose2",
            pose2,
            "--model",
            str(fusion_dir),
            "--cell",
            str(CELL),
            "-o",
            str(out / "fused"),
        ]
    )
    err = capsys.readouterr().err
    assert rc == 1, err
    assert want in err
    assert "error" in err
    assert _files(out) == set()


def test_fuse_cell_mismatch_with_model(tmp_path, fusion_dir, capsys):
    p = _save_map(tmp_path / "a.npz", *_masses(1), cell=np.float64(0.32))
    rc = cli.main(fuse_args(p, p, fusion_dir, str(tmp_path / "o")))
    assert rc == 1 and "trained on 0.5 m cells" in capsys.readouterr().err
    assert not (tmp_path / "o.npz").exists()


def test_parse_pose_and_masses_hand_cases(tmp_path):
    np.testing.assert_allclose(cli.parse_pose("1, -2.5, 0.25", "--pose1"), [1.0, -2.5, 0.25])
    for bad in ("1,2", "a,b,c", "1,2,nan", "1,2,3,4"):
        with pytest.raises(cli.CliError, match="--pose1"):
            cli.parse_pose(bad, "--pose1")
    # a sum just above 1 within the tolerance is accepted and renormalised onto the simplex
    mf = np.full((16, 16), 0.5 + 4e-5, np.float32)
    m, cell = cli.load_masses(_save_map(tmp_path / "t.npz", mf, mf.copy(), cell=np.float32(0.32)))
    assert m.shape == (2, 16, 16) and m.sum(0).max() <= 1.0 + 1e-6 and cell == pytest.approx(0.32)


def test_risk_verdict_hand_cases():
    v = cli.risk_verdict(1 / 30, speed=10.0)  # risk 1/30 <=> THW = 1.5 s exactly: not critical
    assert (
        v["thw_s"] == pytest.approx(1.5) and not v["critical"] and v["gap_m"] == pytest.approx(15.0)
    )
    v = cli.risk_verdict(0.05, speed=None)  # THW = 1 s
    assert v["thw_s"] == pytest.approx(1.0) and v["critical"] and "gap_m" not in v
    v = cli.risk_verdict(0.0, speed=5.0)  # no vehicle ahead
    assert (
        v["thw_s"] == float("inf") and v["verdict"] == "uncritical" and v["gap_m"] == float("inf")
    )
    assert cli.risk_verdict(-0.01, None)["thw_s"] == float("inf")


# ------------------------------------------------------------------ risk


def test_risk_pair_round_trip_equals_library(tmp_path, risk_dir, stereo_pair, capsys):
    left, right = stereo_pair
    cv2.imwrite(str(tmp_path / "f_left.png"), left)
    cv2.imwrite(str(tmp_path / "f_right.png"), right)
    params = tmp_path / "params.yaml"
    params.write_text(
        "risk_data:\n  sgm: {num_disparities: 32, block_size: 5}\n  orb: {max_dy: 5.0}\n"
    )
    rc = cli.main(
        [
            "risk",
            str(tmp_path / "f_left.png"),
            str(tmp_path / "f_right.png"),
            "--speed",
            "12",
            "--model",
            str(risk_dir),
            "--params",
            str(params),
            "-o",
            str(tmp_path / "r.json"),
        ]
    )
    assert rc == 0
    res = json.loads(capsys.readouterr().out)
    assert json.loads((tmp_path / "r.json").read_text())["risk"] == pytest.approx(res["risk"])
    disp = compute_disparity(left, right, num_disparities=32, block_size=5)
    orb = check_pair(left, right, max_dy=5.0)
    p = load_risk_model(risk_dir).predict(left_bgr=left[None], disp_sgm=disp[None])[0]
    assert res["risk"] == pytest.approx(float(p), abs=1e-6)
    assert res["orb_outlier"] == orb.outlier is False and res["orb_mean_dx"] == pytest.approx(
        orb.mean_dx
    )
    assert res["disp_median_px"] == pytest.approx(6.0, abs=1.0)
    assert (
        res["critical"] == (res["thw_s"] is not None and res["thw_s"] < 1.5)
        and res["speed_m_s"] == 12.0
    )


def test_risk_folder_writes_csv(tmp_path, risk_dir, stereo_pair, capsys):
    left, right = stereo_pair
    d = tmp_path / "pairs"
    d.mkdir()
    for i in range(2):
        cv2.imwrite(str(d / f"{i:03d}_left.png"), np.roll(left, 8 * i, axis=1))
        cv2.imwrite(str(d / f"{i:03d}_right.png"), np.roll(right, 8 * i, axis=1))
    (d / "notes.txt").write_text("ignored")
    out = tmp_path / "risk.csv"
    assert cli.main(["risk", str(d), "--model", str(risk_dir), "-o", str(out)]) == 0
    rows = list(csv.DictReader(out.open()))
    assert [r["id"] for r in rows] == ["000", "001"]
    capsys.readouterr()
    assert (
        cli.main(
            ["risk", str(d / "001_left.png"), str(d / "001_right.png"), "--model", str(risk_dir)]
        )
        == 0
    )
    single = json.loads(capsys.readouterr().out)
    assert float(rows[1]["risk"]) == pytest.approx(single["risk"], abs=1e-6)


@pytest.mark.parametrize(
    "case", ["unreadable", "size_mismatch", "missing", "unpaired", "empty_folder", "bad_speed"]
)
def test_risk_bad_input_errors_and_writes_nothing(tmp_path, risk_dir, stereo_pair, case, capsys):
    left, right = stereo_pair
    d = tmp_path / "in"
    d.mkdir()
    cv2.imwrite(str(d / "a_left.png"), left)
    cv2.imwrite(str(d / "a_right.png"), right)
    args = [str(d / "a_left.png"), str(d / "a_right.png")]
    extra: list[str] = []
    if case == "unreadable":
        (d / "a_right.png").write_bytes(b"\x89PNG garbage")
        want = "not a readable image"
    elif case == "size_mismatch":
        cv2.imwrite(str(d / "a_right.png"), right[:, :-8])
        want = "differs from"
    elif case == "missing":
        args[1], want = str(d / "nope.png"), "not found"
    elif case == "unpaired":
        cv2.imwrite(str(d / "b_left.png"), left)
        args, want = [str(d)], "no partner image 'b_right"
    elif case == "empty_folder":
        e = tmp_path / "empty"
        e.mkdir()
        args, want = [str(e)], "no stereo pairs"
    else:
        extra, want = ["--speed", "-3"], "--speed"
    out = tmp_path / "out"
    out.mkdir()
    rc = cli.main(["risk", *args, "--model", str(risk_dir), *extra, "-o", str(out / "res.csv")])
    err = capsys.readouterr().err
    assert rc == 1 and want in err, err
    assert _files(out) == set()


def test_risk_missing_alias(tmp_path, cl, stereo_pair, capsys):
    left, right = stereo_pair
    cv2.imwrite(str(tmp_path / "l.png"), left)
    cv2.imwrite(str(tmp_path / "r.png"), right)
    assert (
        cli.main(["risk", str(tmp_path / "l.png"), str(tmp_path / "r.png"), "--model", "champion"])
        == 1
    )
    err = capsys.readouterr().err
    assert "traffictwin-risk" in err and "champion" in err


# ------------------------------------------------------------------ registry / runs subcommands


def test_rollback_unknown_model_and_runs_compare(tmp_path, cl, mlflow_uri, capsys):
    import mlflow

    assert (
        cli.main(
            ["rollback", "--model", "traffictwin-fusion-Z", "--log", str(tmp_path / "log.jsonl")]
        )
        == 1
    )
    assert "no registered model 'traffictwin-fusion-Z'" in capsys.readouterr().err
    assert not (tmp_path / "log.jsonl").exists()
    mlflow.set_tracking_uri(mlflow_uri)
    mlflow.set_experiment("fusion")
    with mlflow.start_run(run_name="fusion-B"):
        mlflow.log_metric("test/kld_fo_mean", 0.123)
    assert cli.main(["runs", "compare", "--experiment", "fusion"]) == 0
    out = capsys.readouterr().out
    assert "fusion-B" in out and "0.123" in out
    assert cli.main(["runs", "compare", "--experiment", "nope"]) == 1
    assert "'nope' not found" in capsys.readouterr().err


@pytest.mark.integration
def test_console_script_exit_status(tmp_path):
    """The installed `traffictwin` entry point: usage errors exit 2, input errors 1 with the message."""
    exe = Path(sys.executable).parent / "traffictwin"
    proc = subprocess.run([str(exe), "fuse", "x.npz"], capture_output=True, text=True, cwd=tmp_path)
    assert proc.returncode == 2 and "--pose1" in proc.stderr
    proc = subprocess.run(
        [str(exe), "fuse", "x.npz", "y.npz", "--pose1", "0,0,0", "--pose2", "0,0,0", "-o", "o"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert proc.returncode == 1 and "x.npz: file not found" in proc.stderr
    assert not any(tmp_path.iterdir())


def test_promote_is_a_project_workflow_not_a_command(capsys):
    """Promotion needs the project's params and data: `python -m pipelines.promote`, not the CLI."""
    with pytest.raises(SystemExit) as exc:
        cli.main(["promote", "--dry-run"])
    assert exc.value.code == 2 and "invalid choice: 'promote'" in capsys.readouterr().err


def test_rollback_logs_to_the_recorded_promotion_log(tmp_path, mlflow_uri, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    cl = reg.client(mlflow_uri)
    log = tmp_path / "reports" / "promotions.jsonl"
    gate = reg.Gate("test/w", "max", 0.0)
    for w in (1.0, 2.0):
        mv = reg.ensure_version(cl, "traffictwin-fusion-X", log_linear(w))
        d = reg.decide(cl, "traffictwin-fusion-X", mv, lambda uri: {"test/w": float(uri[-1])}, gate)
        reg.apply(cl, d, log_path=log)
    assert str(reg.get_alias(cl, "traffictwin-fusion-X", "champion").version) == "2"
    assert cli.main(["rollback", "--model", "traffictwin-fusion-X"]) == 0
    assert "champion v2 -> v1" in capsys.readouterr().out
    assert [r["event"] for r in reg.read_log(log)] == ["promotion", "promotion", "rollback"]
    # status lists it
    assert cli.main(["status", "--json"]) == 0
    (row,) = json.loads(capsys.readouterr().out)
    assert row["champion"]["version"] == "1" and row["history"] == ["1"]


def test_bare_alias_without_a_registered_fusion_model_names_it(tmp_path, cl, capsys):
    p1 = _save_map(tmp_path / "a.npz", *_masses(4))
    args = ["fuse", str(p1), str(p1), "--pose1", POSE1, "--pose2", POSE2, "--model", "champion"]
    assert cli.main([*args, "-o", str(tmp_path / "o")]) == 1
    assert "traffictwin-fusion" in capsys.readouterr().err
    assert not list(tmp_path.glob("o*"))


def test_stereo_settings_from_model_domain_then_params_file(tmp_path):
    domain = {"camera": {"width": 320, "height": 160}, "sgm": {"num_disparities": 48}, "orb": {}}
    params = tmp_path / "p.yaml"
    params.write_text("risk_data:\n  sgm: {num_disparities: 32}\n  orb: {max_dy: 4.0}\n")
    st = cli.stereo_settings(domain, str(params), "models/risk/rgbd")
    assert st.sgm == {"num_disparities": 48} and st.orb == {}
    assert st.source == "metadata of models/risk/rgbd"
    st = cli.stereo_settings({"label": "risk"}, str(params))  # no sgm/orb in the domain
    assert (st.sgm, st.orb, st.source) == ({"num_disparities": 32}, {"max_dy": 4.0}, str(params))
    assert cli.stereo_settings(None, None).source == "library defaults"
    with pytest.raises(cli.CliError, match="params_path: .*nope.yaml not found"):
        cli.stereo_settings(None, str(tmp_path / "nope.yaml"))


def test_risk_uses_the_model_domain(tmp_path, stereo_pair, capsys):
    """A model whose metadata records the SGM settings of its data: the CLI uses them."""
    left, right = stereo_pair
    cv2.imwrite(str(tmp_path / "f_left.png"), left)
    cv2.imwrite(str(tmp_path / "f_right.png"), right)
    torch.manual_seed(1)
    d = save_risk_model(
        Dave2(Dave2Config()).eval(),
        tmp_path / "m",
        {"label": "risk", "domain": {"sgm": {"num_disparities": 16, "block_size": 7}}},
    )
    args = ["risk", str(tmp_path / "f_left.png"), str(tmp_path / "f_right.png"), "--model", str(d)]
    assert cli.main(args) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["stereo_settings"] == f"metadata of {d}"
    disp = compute_disparity(left, right, num_disparities=16, block_size=7)
    p = load_risk_model(d).predict(left_bgr=left[None], disp_sgm=disp[None])[0]
    assert res["risk"] == pytest.approx(float(p), abs=1e-6)
