"""The CLI never destroys a file, refuses inputs outside the
model's training domain, fails fast and clearly without a registry, and handles many inputs in
one call (batched fusion, streamed risk) with the same results as one at a time."""

from __future__ import annotations

import csv
import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
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
    write_pair,
)

from traffictwin import api, cli
from traffictwin.risk.model_io import RiskModel, load_risk_model
from traffictwin.stereo.sgm import compute_disparity

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def fusion_dir(tmp_path_factory) -> Path:
    return save_fusion_model(tmp_path_factory.mktemp("fusion") / "m")


@pytest.fixture(scope="module")
def risk_dir(tmp_path_factory) -> Path:
    """A model without speed input and without domain metadata."""
    return save_risk(tmp_path_factory.mktemp("risk") / "m")


@pytest.fixture(scope="module")
def pair() -> tuple[np.ndarray, np.ndarray]:
    return textured_pair()


def _listing(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def _one_error_line(err: str, *needles: str) -> str:
    lines = [ln for ln in err.strip().splitlines() if ln]
    assert len(lines) == 1, err
    for n in needles:
        assert n in lines[0], lines[0]
    return lines[0]


# ------------------------------------------------------------------ outputs


def test_output_naming_an_input_is_refused_and_the_input_kept(
    tmp_path, fusion_dir, risk_dir, pair, capsys
):
    p1 = save_map(tmp_path / "a.npz", *masses(1), cell=np.float64(CELL))
    p2 = save_map(tmp_path / "b.npz", *masses(2))
    lp, rp = write_pair(tmp_path, "f", *pair)
    (tmp_path / "link.json").symlink_to(lp)  # a second name of the left image
    before = _listing(tmp_path)
    # fuse -o a  -> a.npz is map 1
    assert cli.main(fuse_args(p1, p2, fusion_dir, tmp_path / "a")) == 1
    _one_error_line(capsys.readouterr().err, "a.npz", "input", "refusing to overwrite")
    # risk -o LEFT.png (a PNG replaced by JSON) and through a symlink; --force does not change it
    for out in (lp, tmp_path / "link.json"):
        rc = cli.main(
            ["risk", str(lp), str(rp), "--model", str(risk_dir), "-o", str(out), "--force"]
        )
        assert rc == 1
        _one_error_line(capsys.readouterr().err, "input")
    assert _listing(tmp_path) == before


def test_existing_output_needs_force(tmp_path, fusion_dir, capsys):
    p1 = save_map(tmp_path / "a.npz", *masses(1), cell=np.float64(CELL))
    p2 = save_map(tmp_path / "b.npz", *masses(2))
    (tmp_path / "out.png").write_bytes(b"keep me")
    # a file that is no previous output: refused, and --force is not offered (it would not help)
    assert cli.main(fuse_args(p1, p2, fusion_dir, tmp_path / "out")) == 1
    line = _one_error_line(capsys.readouterr().err, "out.png exists and is not a previous .png")
    assert "--force" not in line
    assert (tmp_path / "out.png").read_bytes() == b"keep me" and not (tmp_path / "out.npz").exists()
    assert cli.main([*fuse_args(p1, p2, fusion_dir, tmp_path / "out"), "--force"]) == 1
    _one_error_line(capsys.readouterr().err, "out.png exists and is not a previous .png output")
    assert (tmp_path / "out.png").read_bytes() == b"keep me"
    # a PNG that no traffictwin command wrote (no preview marker) is not replaced either
    cv2.imwrite(str(tmp_path / "out.png"), np.zeros((4, 4, 3), np.uint8))
    foreign = (tmp_path / "out.png").read_bytes()
    assert cli.main([*fuse_args(p1, p2, fusion_dir, tmp_path / "out"), "--force"]) == 1
    _one_error_line(capsys.readouterr().err, "not a previous .png output", "its content is png")
    assert (tmp_path / "out.png").read_bytes() == foreign
    # a previous output of the command: "pass --force", and --force replaces it
    (tmp_path / "out.png").unlink()
    assert cli.main(fuse_args(p1, p2, fusion_dir, tmp_path / "out")) == 0
    assert cli.main(fuse_args(p1, p2, fusion_dir, tmp_path / "out")) == 1
    _one_error_line(capsys.readouterr().err, "out.npz exists (a fused grid", "pass --force")
    assert cli.main([*fuse_args(p1, p2, fusion_dir, tmp_path / "out"), "--force"]) == 0
    assert cv2.imread(str(tmp_path / "out.png")) is not None and (tmp_path / "out.npz").exists()


def test_output_that_is_a_directory_is_one_line(tmp_path, risk_dir, pair, capsys):
    lp, rp = write_pair(tmp_path / "in", "f", *pair)
    (tmp_path / "res.json").mkdir()
    rc = cli.main(
        ["risk", str(lp), str(rp), "--model", str(risk_dir), "-o", str(tmp_path / "res.json")]
    )
    assert rc == 1
    _one_error_line(capsys.readouterr().err, "res.json is a directory")


def test_missing_parent_folders_are_created_by_every_command(
    tmp_path, fusion_dir, risk_dir, pair, capsys
):
    p1 = save_map(tmp_path / "a.npz", *masses(1), cell=np.float64(CELL))
    p2 = save_map(tmp_path / "b.npz", *masses(2))
    lp, rp = write_pair(tmp_path / "frames", "f", *pair)
    new = tmp_path / "new"
    assert cli.main(fuse_args(p1, p2, fusion_dir, new / "fuse" / "x" / "out")) == 0
    assert (new / "fuse" / "x" / "out.npz").is_file()
    assert (
        cli.main(
            ["risk", str(lp), str(rp), "--model", str(risk_dir), "-o", str(new / "risk" / "r.json")]
        )
        == 0
    )
    assert (new / "risk" / "r.json").is_file()
    assert (
        cli.main(
            [
                "risk",
                str(tmp_path / "frames"),
                "--model",
                str(risk_dir),
                "-o",
                str(new / "csv" / "r.csv"),
            ]
        )
        == 0
    )
    assert (new / "csv" / "r.csv").is_file()
    tw = ["twin", str(p1), str(p2), "--pose", POSE1, "--pose", POSE2, "--method", "naive"]
    assert cli.main([*tw, "--cell", str(CELL), "-o", str(new / "twin" / "t")]) == 0
    assert (new / "twin" / "t.npz").is_file()
    assert (
        cli.main(["export", "risk", "--model", str(risk_dir), "-o", str(new / "exp" / "r.pt")]) == 0
    )
    assert (new / "exp" / "r.pt").is_file()
    capsys.readouterr()


def test_a_failing_command_leaves_no_file_and_no_created_folder(tmp_path, risk_dir, pair, capsys):
    d = tmp_path / "frames"
    write_pair(d, "a", *pair)
    write_pair(d, "b", *pair)
    (d / "b_right.png").write_bytes(b"\x89PNG garbage")  # found only when its batch is read
    out = tmp_path / "deep" / "er" / "r.csv"
    assert (
        cli.main(["risk", str(d), "--model", str(risk_dir), "--batch-size", "1", "-o", str(out)])
        == 1
    )
    _one_error_line(capsys.readouterr().err, "b_right.png", "not a readable image")
    assert not (tmp_path / "deep").exists()


# ------------------------------------------------------------------ registry


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_unreachable_registry_is_one_line(tmp_path, risk_dir, pair, capsys, monkeypatch):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    lp, rp = write_pair(tmp_path, "f", *pair)
    uri = f"http://127.0.0.1:{_free_port()}"
    rc = cli.main(["risk", str(lp), str(rp), "--tracking-uri", uri, "-o", str(tmp_path / "r.json")])
    assert rc == 1
    _one_error_line(capsys.readouterr().err, uri, "unreachable")
    assert cli.main(["status", "--tracking-uri", uri]) == 1
    _one_error_line(capsys.readouterr().err, "unreachable")
    assert not (tmp_path / "r.json").exists()


def test_missing_alias_is_one_line(tmp_path, cl, pair, capsys):
    lp, rp = write_pair(tmp_path, "f", *pair)
    assert cli.main(["risk", str(lp), str(rp), "--model", "traffictwin-risk@challenger"]) == 1
    _one_error_line(capsys.readouterr().err, "traffictwin-risk", "challenger")


def _bare_env() -> dict[str, str]:
    env = {
        k: v for k, v in os.environ.items() if not k.startswith(("MLFLOW_", "TRAFFICTWIN_", "DVC_"))
    }
    env["PYTHONPATH"] = os.pathsep.join((str(ROOT / "src"), str(ROOT)))
    return env


@pytest.mark.integration  # a CLI subprocess
def test_no_stray_mlflow_db_outside_the_project(tmp_path, pair, monkeypatch, capsys):
    """Run in an empty folder with no URI: one clear line, nothing created. The first command in a
    fresh process with the bare environment (nothing inherited from the test session), the rest
    in-process with the same environment."""
    work = tmp_path / "empty"
    work.mkdir()
    lp, rp = write_pair(tmp_path / "in", "f", *pair)
    m1 = save_map(tmp_path / "in" / "a.npz", *masses(1), cell=np.float64(CELL))
    first, *rest = [
        ["risk", str(lp), str(rp)],
        ["fuse", str(m1), str(m1), "--pose1", POSE1, "--pose2", POSE2, "-o", "o"],
        ["status"],
        ["rollback", "--model", "traffictwin-risk"],
        ["runs", "compare", "--experiment", "fusion"],
        ["risk", str(lp), str(rp), "--tracking-uri", "sqlite:///other.db"],
    ]
    proc = subprocess.run(
        [sys.executable, "-m", "traffictwin.cli", *first],
        cwd=work,
        env=_bare_env(),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 1, (first, proc.stderr)
    line = _one_error_line(proc.stderr, "error")
    assert "--tracking-uri" in line or "not creating" in line, line
    assert list(work.iterdir()) == []
    for k in [k for k in os.environ if k.startswith(("MLFLOW_", "TRAFFICTWIN_", "DVC_"))]:
        monkeypatch.delenv(k)
    monkeypatch.chdir(work)
    for args in rest:
        assert cli.main(args) == 1, (args, capsys.readouterr().err)
        line = _one_error_line(capsys.readouterr().err, "error")
        assert "--tracking-uri" in line or "not creating" in line, line
        assert list(work.iterdir()) == [], (args, list(work.iterdir()))


# ------------------------------------------------------------------ training domain


def test_fusion_grid_must_be_the_training_grid(tmp_path, fusion_dir, capsys):
    big = [
        save_map(tmp_path / f"{k}.npz", *masses(k, 2 * H, W), cell=np.float64(CELL)) for k in (1, 2)
    ]
    assert cli.main(fuse_args(*big, fusion_dir, tmp_path / "o")) == 1
    _one_error_line(capsys.readouterr().err, f"grid {2 * H}x{W}", f"trained on {H}x{W}")
    small_cell = [
        save_map(tmp_path / f"c{k}.npz", *masses(k), cell=np.float64(0.32)) for k in (1, 2)
    ]
    assert cli.main(fuse_args(*small_cell, fusion_dir, tmp_path / "o")) == 1
    _one_error_line(capsys.readouterr().err, "trained on 0.5 m cells")
    assert not list(tmp_path.glob("o.*"))


def test_image_size_must_be_the_training_camera_or_resized(tmp_path, pair, capsys):
    d = save_risk(
        tmp_path / "m", {"label": "risk", "domain": {"camera": {"width": 320, "height": 160}}}
    )
    small = textured_pair(seed=5, w=200, h=120)
    lp, rp = write_pair(tmp_path, "s", *small)
    args = ["risk", str(lp), str(rp), "--model", str(d)]
    assert cli.main(args) == 1
    _one_error_line(capsys.readouterr().err, "200x120", "320x160", "--resize")
    assert cli.main([*args, "--resize"]) == 0
    res = json.loads(capsys.readouterr().out)
    left, right = (cv2.resize(im, (320, 160), interpolation=cv2.INTER_AREA) for im in small)
    disp = compute_disparity(left, right)
    want = load_risk_model(d).predict(left_bgr=left[None], disp_sgm=disp[None])[0]
    assert res["risk"] == pytest.approx(float(want), abs=1e-6)
    # the disparity is in the camera's pixel scale: shift 6 px at 200 px wide -> 9.6 px at 320
    assert res["disp_median_px"] == pytest.approx(6 * 320 / 200, abs=1.0)


def test_speed_outside_training_range_and_speed_ignored_by_model(tmp_path, pair, risk_dir, capsys):
    lp, rp = write_pair(tmp_path, "f", *pair)
    d = save_risk(
        tmp_path / "speed", {"label": "risk", "domain": {"max_speed": 25.0}}, use_speed=True
    )
    base = ["risk", str(lp), str(rp), "--model", str(d)]
    for bad in ("1e30", "30"):
        assert cli.main([*base, "--speed", bad]) == 1
        _one_error_line(capsys.readouterr().err, "--speed", "[0, 25] m/s")
    assert cli.main([*base, "--speed", "12"]) == 0
    assert json.loads(capsys.readouterr().out)["speed_m_s"] == 12.0
    # a model without a range: the params file's risk_data.max_speed
    d2 = save_risk(tmp_path / "speed2", use_speed=True)
    params = tmp_path / "p.yaml"
    params.write_text("risk_data:\n  max_speed: 20.0\n")
    rc = cli.main(
        ["risk", str(lp), str(rp), "--model", str(d2), "--speed", "21", "--params", str(params)]
    )
    assert rc == 1
    _one_error_line(capsys.readouterr().err, "[0, 20] m/s", "p.yaml")
    # a model without speed input: a one-line warning, the result is computed
    assert cli.main(["risk", str(lp), str(rp), "--model", str(risk_dir), "--speed", "10"]) == 0
    out = capsys.readouterr()
    _one_error_line(out.err, "warning", "no speed input")
    assert json.loads(out.out)["speed_m_s"] == 10.0


@pytest.mark.parametrize("raw", [-0.027, 1.7, 0.0])
def test_risk_clamped_and_thw_has_one_encoding(tmp_path, risk_dir, pair, raw, monkeypatch, capsys):
    """Whatever the network gives, the risk is in [0, 1]; THW / gap are null in JSON and empty in
    CSV when nothing is ahead, never inf."""
    monkeypatch.setattr(
        RiskModel, "predict", lambda self, **kw: np.full(len(kw["left_bgr"]), raw, np.float32)
    )
    lp, rp = write_pair(tmp_path / "frames", "f", *pair)
    args = ["risk", str(lp), str(rp), "--model", str(risk_dir), "--speed", "10"]
    assert cli.main([*args, "-o", str(tmp_path / "r.json")]) == 0
    res = json.loads((tmp_path / "r.json").read_text())
    want = min(max(raw, 0.0), 1.0)
    assert res["risk"] == pytest.approx(want)
    if want == 0.0:
        assert res["thw_s"] is None and res["gap_m"] is None and not res["critical"]
    else:
        assert res["thw_s"] == pytest.approx(1 / (20 * want))
    assert "Infinity" not in (tmp_path / "r.json").read_text()
    assert (
        cli.main(
            [
                "risk",
                str(tmp_path / "frames"),
                "--model",
                str(risk_dir),
                "--speed",
                "10",
                "-o",
                str(tmp_path / "r.csv"),
            ]
        )
        == 0
    )
    text = (tmp_path / "r.csv").read_text()
    (row,) = csv.DictReader(text.splitlines())
    assert float(row["risk"]) == pytest.approx(want) and "inf" not in text
    assert (row["thw_s"] == "") == (want == 0.0) and (row["gap_m"] == "") == (want == 0.0)
    capsys.readouterr()


# ------------------------------------------------------------------ many inputs per call


def test_fuse_pairs_batched_equals_one_by_one(tmp_path, fusion_dir, capsys):
    d = tmp_path / "maps"
    d.mkdir()
    rows = []
    for k in range(5):
        a = save_map(d / f"{k}a.npz", *masses(10 + k), cell=np.float64(CELL))
        b = save_map(d / f"{k}b.npz", *masses(20 + k))
        pose2 = f"{1.0 + k},{-0.5 * k},{0.05 * k}"
        rows.append((f"p{k}", a.name, b.name, "0", "0", "0", *pose2.split(",")))
        assert (
            cli.main(
                [
                    "fuse",
                    str(a),
                    str(b),
                    "--pose1",
                    "0,0,0",
                    "--pose2",
                    pose2,
                    "--model",
                    str(fusion_dir),
                    "-o",
                    str(tmp_path / "one" / f"p{k}"),
                ]
            )
            == 0
        )
    lst = d / "pairs.csv"
    with open(lst, "w", newline="") as fh:
        wr = csv.writer(fh)
        wr.writerow(["id", "map1", "map2", "x1", "y1", "yaw1", "x2", "y2", "yaw2"])
        wr.writerows(rows)
    capsys.readouterr()
    out = tmp_path / "many"
    assert (
        cli.main(
            [
                "fuse",
                "--pairs",
                str(lst),
                "--model",
                str(fusion_dir),
                "--batch-size",
                "2",
                "-o",
                str(out),
            ]
        )
        == 0
    )
    summary = list(csv.DictReader((out / "summary.csv").open()))
    assert [r["id"] for r in summary] == [f"p{k}" for k in range(5)]
    for k in range(5):
        a, b = np.load(tmp_path / "one" / f"p{k}.npz"), np.load(out / f"p{k}.npz")
        for key in ("m_free", "m_occ", "u", "rel_pose"):
            np.testing.assert_allclose(b[key], a[key], atol=1e-5)
        assert (out / f"p{k}.png").is_file()
    # a folder of <id>_1.npz / <id>_2.npz carrying their poses gives the same
    f = tmp_path / "folder"
    f.mkdir()
    for k in range(5):
        pose2 = np.array([1.0 + k, -0.5 * k, 0.05 * k])
        save_map(f / f"p{k}_1.npz", *masses(10 + k), cell=np.float64(CELL), pose=np.zeros(3))
        save_map(f / f"p{k}_2.npz", *masses(20 + k), pose=pose2)
    out2 = tmp_path / "many2"
    assert (
        cli.main(
            ["fuse", "--pairs", str(f), "--model", str(fusion_dir), "--no-preview", "-o", str(out2)]
        )
        == 0
    )
    for k in range(5):
        np.testing.assert_allclose(
            np.load(out2 / f"p{k}.npz")["m_occ"], np.load(out / f"p{k}.npz")["m_occ"], atol=1e-5
        )
    assert not list(out2.glob("*.png"))
    # the list names an output that exists: refused without --force, nothing replaced
    before = _listing(out)
    assert cli.main(["fuse", "--pairs", str(lst), "--model", str(fusion_dir), "-o", str(out)]) == 1
    _one_error_line(capsys.readouterr().err, "exists", "--force")
    assert _listing(out) == before


def test_fuse_pairs_bad_list_is_one_line(tmp_path, fusion_dir, capsys):
    lst = tmp_path / "pairs.csv"
    lst.write_text("map1,map2\nnope.npz,nope2.npz\n")
    assert (
        cli.main(
            ["fuse", "--pairs", str(lst), "--model", str(fusion_dir), "-o", str(tmp_path / "o")]
        )
        == 1
    )
    _one_error_line(capsys.readouterr().err, "nope.npz", "not found")
    assert not (tmp_path / "o").exists()


def test_risk_folder_streamed_in_batches_equals_one_by_one(tmp_path, pair, capsys):
    d = save_risk(
        tmp_path / "speed", {"label": "risk", "domain": {"max_speed": 25.0}}, use_speed=True
    )
    frames = tmp_path / "frames"
    for k in range(5):
        write_pair(
            frames, f"{k:03d}", np.roll(pair[0], 7 * k, axis=1), np.roll(pair[1], 7 * k, axis=1)
        )
    out = tmp_path / "r.csv"
    assert (
        cli.main(
            [
                "risk",
                str(frames),
                "--model",
                str(d),
                "--speed",
                "8",
                "--batch-size",
                "2",
                "-o",
                str(out),
            ]
        )
        == 0
    )
    rows = list(csv.DictReader(out.open()))
    assert [r["id"] for r in rows] == [f"{k:03d}" for k in range(5)]
    capsys.readouterr()
    for k, row in enumerate(rows):
        lp, rp = frames / f"{k:03d}_left.png", frames / f"{k:03d}_right.png"
        assert cli.main(["risk", str(lp), str(rp), "--model", str(d), "--speed", "8"]) == 0
        single = json.loads(capsys.readouterr().out)
        assert float(row["risk"]) == pytest.approx(single["risk"], abs=1e-6)
        assert float(row["disp_median_px"]) == pytest.approx(single["disp_median_px"])


def test_assess_risk_reads_images_one_batch_at_a_time(tmp_path, risk_dir, pair, monkeypatch):
    """Memory bound: images are decoded only when their batch comes (the generator never reads
    ahead more than one batch)."""
    frames = [api.Frame(str(k), *write_pair(tmp_path, f"{k}", *pair)) for k in range(6)]
    reads: list[str] = []
    real = api.read_image  # patched where assess_risk's pair reader looks it up (api.pairs)
    monkeypatch.setattr(api.pairs, "read_image", lambda p: reads.append(str(p)) or real(p))
    rows = api.assess_risk(api.load_risk(risk_dir), frames, batch_size=2)
    next(rows)
    assert len(reads) == 4  # the first batch: 2 frames x (left, right)
    assert len(list(rows)) == 5 and len(reads) == 12


def test_inputs_the_model_would_ignore_or_contradict_are_refused(tmp_path, fusion_dir, capsys):
    p1 = save_map(tmp_path / "a.npz", *masses(1), cell=np.float64(CELL))
    p2 = save_map(tmp_path / "b.npz", *masses(2))
    base = fuse_args(p1, p2, fusion_dir, tmp_path / "o")
    assert cli.main([*base, "--cell", "0.32"]) == 1  # a.npz says 0.5 m
    _one_error_line(capsys.readouterr().err, "--cell", "0.5")
    # one network serves every pose-noise level: there is no configuration to name
    with pytest.raises(SystemExit) as exc:
        cli.main([*base, "--config", "D"])
    assert exc.value.code == 2 and "--config" in capsys.readouterr().err
    assert cli.main(base) == 0  # consistent: fine


def test_resolve_tracking_uri_never_creates_a_store(tmp_path, monkeypatch):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    db = tmp_path / "x.db"
    with pytest.raises(api.ApiError, match="no MLflow database .*not creating one"):
        api.resolve_tracking_uri(f"sqlite:///{db}")
    with pytest.raises(api.ApiError, match="no MLflow file store"):
        api.resolve_tracking_uri(str(tmp_path / "mlruns"))
    assert not db.exists() and not (tmp_path / "mlruns").exists()
    db.write_bytes(b"")
    assert api.resolve_tracking_uri(f"sqlite:///{db}") == f"sqlite:///{db}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "http://example.invalid:5000")
    assert api.resolve_tracking_uri() == "http://example.invalid:5000"  # a server: probed later
    # inside the project without a URI: the project's database
    monkeypatch.delenv("MLFLOW_TRACKING_URI")
    monkeypatch.setenv("TRAFFICTWIN_REPO_ROOT", str(tmp_path))
    (tmp_path / "dvc.yaml").write_text("stages: {}\n")
    with pytest.raises(api.ApiError, match=f"no MLflow database at {tmp_path / 'mlflow.db'}"):
        api.resolve_tracking_uri()
    assert not (tmp_path / "mlflow.db").exists()
