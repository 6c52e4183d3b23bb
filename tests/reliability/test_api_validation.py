"""The Python API raises its own errors (``ApiError``
subclasses, in API terms) and applies the CLI's mass, pose, cell and grid checks; the CLI turns
the remaining bad inputs (twin grids, pair lists, params files, thresholds) into one line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from _cli_models import (
    CELL,
    POSE1,
    POSE2,
    H,
    W,
    masses,
    save_fusion_model,
    save_map,
    save_risk,
    textured_pair,
    write_pair,
)

from traffictwin import api, cli


@pytest.fixture(scope="module")
def fusion(tmp_path_factory) -> api.FusionModel:
    return api.load_fusion(save_fusion_model(tmp_path_factory.mktemp("f") / "m"))


@pytest.fixture(scope="module")
def risk_dir(tmp_path_factory) -> Path:
    return save_risk(
        tmp_path_factory.mktemp("r") / "m",
        {"label": "risk", "domain": {"speed_range": [0.0, 20.0]}},
        use_speed=True,
    )


def _pair(**kw) -> api.FusePair:
    m1, m2 = np.stack(masses(1)), np.stack(masses(2))
    base = {"m1": m1, "m2": m2, "pose1": [1.0, 2.0, 0.1], "pose2": [4.0, 1.0, -0.05]}
    return api.FusePair(**{**base, "cell": CELL, "id": "p", **kw})


def _one_line(capsys, *needles: str) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    for n in needles:
        assert n in err[0], err[0]
    return err[0]


# ------------------------------------------------------------------ api.fuse checks


def test_api_fuse_accepts_valid_masses(fusion):
    (res,) = api.fuse(fusion, [_pair()])
    assert res.masses.shape == (2, H, W) and np.isfinite(res.masses).all()


@pytest.mark.parametrize(
    ("change", "needle"),
    [
        ({"m1": np.full((2, H, W), np.nan, np.float32)}, "outside the simplex|finite|NaN"),
        ({"m1": -np.stack(masses(1))}, "outside the simplex"),
        ({"m2": np.full((2, H, W), 5.0, np.float32)}, "outside the simplex"),
        ({"m1": np.stack(masses(1)).astype(np.complex64)}, "real float array"),
        ({"m1": np.stack(masses(1))[:1]}, r"must be \(2, H, W\)"),
        ({"pose1": [1.0, 2.0]}, "pose1: expected 3 finite real numbers"),
        ({"pose2": [1.0, 2.0, np.inf]}, "pose2: expected 3 finite real numbers"),
        ({"pose1": np.array([1.0, 2.0, 0.1 + 1j])}, "pose1: expected 3 finite real numbers"),
        ({"cell": float("nan")}, "'cell' must be one positive real number"),
        ({"cell": -0.5}, "'cell' must be one positive real number"),
    ],
)
def test_api_fuse_refuses_bad_masses_poses_and_cells(fusion, change, needle):
    with pytest.raises(api.InputValueError, match=needle):
        list(api.fuse(fusion, [_pair(**change)]))


def test_api_fuse_refuses_a_grid_the_model_was_not_trained_on(fusion):
    m = np.stack(masses(1, 48, 48))
    with pytest.raises(api.ModelDomainError, match="trained on 32x48"):
        list(api.fuse(fusion, [_pair(m1=m, m2=m)]))
    with pytest.raises(api.ModelDomainError, match="trained on 0.5 m cells"):
        list(api.fuse(fusion, [_pair(cell=0.25)]))


# ------------------------------------------------------------------ complex in a map


def test_complex_pose_or_cell_in_a_map_file_is_refused(tmp_path):
    p = save_map(tmp_path / "c.npz", *masses(1), pose=np.array([1.0, 2.0, 0.1 + 0.5j]))
    with pytest.raises(api.ApiError, match="'pose': expected 3 finite real numbers"):
        api.load_masses(p)
    q = save_map(tmp_path / "d.npz", *masses(1), cell=np.complex128(0.5 + 0j))
    with pytest.raises(api.ApiError, match="'cell' must be one positive real number"):
        api.load_masses(q)


# ------------------------------------------------------------------ ApiError, API terms


def test_api_errors_are_api_errors_in_api_terms(tmp_path, risk_dir):
    with pytest.raises(api.InputFileError, match="folder not found"):
        api.frames_in_folder(tmp_path / "nonexistent")
    rm = api.load_risk(risk_dir)
    left, right = textured_pair()
    frames = [api.Frame("a", left, right)]
    with pytest.raises(api.InputValueError, match="^speed: expected a number of m/s, got str"):
        list(api.assess_risk(rm, frames, speed="8"))
    with pytest.raises(api.InputValueError, match="^speed: the model .* uses the subject speed"):
        list(api.assess_risk(rm, frames))
    with pytest.raises(api.ModelDomainError, match="^speed: 30 m/s is outside"):
        list(api.assess_risk(rm, frames, speed=30.0))
    gray = [api.Frame("g", left[..., 0], right[..., 0])]  # grayscale arrays work like files
    (row,) = api.assess_risk(rm, gray, speed=8.0)
    assert 0.0 <= row["risk"] <= 1.0
    bad = [api.Frame("f", left.astype(np.float32), right)]
    with pytest.raises(api.InputValueError, match="frame 'f' left: expected an 8-bit"):
        list(api.assess_risk(rm, bad, speed=8.0))
    with pytest.raises(api.InputValueError, match=r"got shape \(160, 320, 2\)"):
        list(api.assess_risk(rm, [api.Frame("c", left[..., :2], right)], speed=8.0))
    for exc in (api.InputFileError, api.InputValueError, api.ModelDomainError):
        assert issubclass(exc, api.ApiError)


# ------------------------------------------------------------------ the CLI's risk


def test_params_file_given_is_never_ignored(tmp_path, risk_dir, capsys):
    lp, rp = write_pair(tmp_path, "f", *textured_pair())
    base = ["risk", str(lp), str(rp), "--speed", "8", "--model", str(risk_dir)]
    assert cli.main([*base, "--params", str(tmp_path / "nonexist.yaml")]) == 1
    _one_line(capsys, "--params:", "nonexist.yaml not found")
    (tmp_path / "bad.yaml").write_text("risk_data: [unclosed\n")
    assert cli.main([*base, "--params", str(tmp_path / "bad.yaml")]) == 1
    _one_line(capsys, "bad.yaml: not valid YAML")


@pytest.mark.parametrize("value", ["inf", "nan", "0", "-1", "1e9"])
def test_thw_threshold_must_be_a_real_headway(tmp_path, risk_dir, value, capsys):
    lp, rp = write_pair(tmp_path, "f", *textured_pair())
    argv = ["risk", str(lp), str(rp), "--speed", "8", "--model", str(risk_dir)]
    assert cli.main([*argv, "--thw-threshold", value]) == 1
    _one_line(capsys, "--thw-threshold: must be a time headway in (0, 10] s")


def test_tiny_images_are_refused_even_with_resize(tmp_path, capsys):
    rdir = save_risk(
        tmp_path / "m", {"label": "risk", "domain": {"camera": {"width": 320, "height": 160}}}
    )
    one = np.full((1, 1, 3), 128, np.uint8)
    lp, rp = write_pair(tmp_path, "t", one, one)
    assert cli.main(["risk", str(lp), str(rp), "--model", str(rdir), "--resize"]) == 1
    _one_line(capsys, "smaller than 32 px")
    small = textured_pair(w=64, h=32)
    lp, rp = write_pair(tmp_path, "s", *small)
    assert cli.main(["risk", str(lp), str(rp), "--model", str(rdir), "--resize"]) == 1
    _one_line(capsys, "enlarged 5.0x", "at most 4x")


# ------------------------------------------------------------------ the twin


def _twin_args(maps: list[Path], out: Path, *extra: str) -> list[str]:
    poses = [a for k in range(len(maps)) for a in ("--pose", POSE1 if k == 0 else POSE2)]
    return ["twin", *map(str, maps), *poses, "-o", str(out), *extra]


def test_twin_refuses_a_grid_its_networks_were_not_trained_on(tmp_path, capsys):
    fdir = save_fusion_model(tmp_path / "f")
    other = [save_map(tmp_path / f"{k}.npz", *masses(k, 48, 48), cell=CELL) for k in (1, 2)]
    argv = _twin_args(other, tmp_path / "o", "--method", "dnn", "--fusion-model", str(fdir))
    assert cli.main(argv) == 1
    _one_line(capsys, "trained on 32x48")
    fine = [save_map(tmp_path / f"c{k}.npz", *masses(k), cell=0.25) for k in (1, 2)]
    argv = _twin_args(fine, tmp_path / "o", "--method", "dnn", "--fusion-model", str(fdir))
    assert cli.main(argv) == 1
    _one_line(capsys, "trained on 0.5 m cells")
    odd = [save_map(tmp_path / f"o{k}.npz", *masses(k, 100, 96), cell=CELL) for k in (1, 2)]
    argv = _twin_args(odd, tmp_path / "o", "--method", "dnn", "--fusion-model", str(fdir))
    assert cli.main(argv) == 1
    _one_line(capsys, "divisible by 16")
    assert not list(tmp_path.glob("o.*"))


# ------------------------------------------------------------------ pair lists


@pytest.mark.parametrize(
    ("row", "needle"),
    [
        ("a,map1.npz", "line 2: 2 field(s), but the header has 3 (id,map1,map2)"),
        ("a,map1.npz,", "line 2: column map2 is empty"),
    ],
)
def test_pair_list_rows_name_what_is_missing(tmp_path, row, needle, capsys):
    save_map(tmp_path / "map1.npz", *masses(1))
    (tmp_path / "pairs.csv").write_text(f"id,map1,map2\n{row}\n")
    fdir = save_fusion_model(tmp_path / "f")
    argv = [
        "fuse",
        "--pairs",
        str(tmp_path / "pairs.csv"),
        "--model",
        str(fdir),
        "--cell",
        str(CELL),
    ]
    assert cli.main([*argv, "-o", str(tmp_path / "out")]) == 1
    _one_line(capsys, needle)


def test_pair_list_pose_column_that_is_not_a_number_is_named(tmp_path, capsys):
    for k in (1, 2):
        save_map(tmp_path / f"m{k}.npz", *masses(k))
    x1, y1, yaw1 = POSE1.split(",")
    (tmp_path / "pairs.csv").write_text(
        f"map1,map2,x1,y1,yaw1,x2,y2,yaw2\nm1.npz,m2.npz,{x1},{y1},{yaw1},4.0,north,0.0\n"
    )
    fdir = save_fusion_model(tmp_path / "f")
    argv = [
        "fuse",
        "--pairs",
        str(tmp_path / "pairs.csv"),
        "--model",
        str(fdir),
        "--cell",
        str(CELL),
    ]
    assert cli.main([*argv, "-o", str(tmp_path / "out")]) == 1
    _one_line(capsys, "line 2: column y2 = 'north' is not a number")


# ------------------------------------------------------------------ OSError, one line


def test_read_only_output_folder_is_one_line(tmp_path, monkeypatch, capsys):
    """A read-only output folder (``EROFS`` / ``EACCES`` on the temp file) gave an ``OSError``
    traceback. Simulated: the suite may run as root, which writes into read-only folders."""
    import errno

    from traffictwin.io import outputs

    fdir = save_fusion_model(tmp_path / "f")
    maps = [save_map(tmp_path / f"{k}.npz", *masses(k), cell=CELL) for k in (1, 2)]

    def read_only(*a, dir=None, **kw):  # noqa: A002 - tempfile's own keyword
        raise OSError(errno.EROFS, "Read-only file system", str(dir))

    monkeypatch.setattr(outputs.tempfile, "mkstemp", read_only)
    argv = ["fuse", *map(str, maps), "--pose1", POSE1, "--pose2", POSE2]
    assert cli.main([*argv, "--model", str(fdir), "-o", str(tmp_path / "ro" / "f")]) == 1
    _one_line(capsys, str(tmp_path / "ro"), "Read-only file system")
    assert not (tmp_path / "ro").exists()  # the folder it created is removed again


def test_oserror_from_a_full_disk_is_one_line_and_leaves_no_temp_file(
    tmp_path, monkeypatch, capsys
):
    """Full disk: the write fails with ENOSPC; the CLI prints one line naming the file and the
    temp files are removed (the export serialises in memory, so no C++ abort)."""
    import errno

    from traffictwin.io import outputs

    fdir = save_fusion_model(tmp_path / "f")
    real = outputs.OutputSet.commit

    def full(self):
        raise OSError(errno.ENOSPC, "No space left on device", str(self.paths[0]))

    monkeypatch.setattr(outputs.OutputSet, "commit", full)
    out = tmp_path / "out" / "m.pt"
    assert cli.main(["export", "fusion", "--model", str(fdir), "-o", str(out)]) == 1
    _one_line(capsys, "m.pt: No space left on device")
    assert not out.parent.exists() or not list(out.parent.iterdir())
    monkeypatch.setattr(outputs.OutputSet, "commit", real)
    assert cli.main(["export", "fusion", "--model", str(fdir), "-o", str(out)]) == 0


@pytest.mark.parametrize(
    ("domain", "needle"),
    [
        ({"speed_range": ["a", "b"]}, "'domain.speed_range' must be [lo, hi] m/s"),
        ({"speed_range": [20.0, 5.0]}, "'domain.speed_range' must be [lo, hi] m/s"),
        ({"max_speed": float("inf")}, "'domain.max_speed' must be a number > 0"),
        ({"sgm": {"num_disparity": 32}}, "'domain.sgm': unknown setting 'num_disparity'"),
        ({"sgm": {"num_disparities": "32"}}, "'domain.sgm': setting 'num_disparities' = '32'"),
        ({"orb": {"max_dy": True}}, "'domain.orb': setting 'max_dy' = True is not a float"),
        ({"camera": [[1, 2], [3, 4], [5, 6], [7, 8]]}, "'domain.camera' must be a mapping"),
        ({"camera": {"width": -320, "height": 160}}, "'domain.camera.width' must be a positive"),
    ],
)
def test_risk_domain_metadata_is_validated_before_use(tmp_path, domain, needle):
    """``speed_range=["a","b"]``, an unknown ``domain.sgm`` key or a 4x2 camera gave
    ``ValueError`` / ``TypeError`` tracebacks when used."""
    rdir = save_risk(tmp_path / "m", {"label": "risk", "domain": domain})
    with pytest.raises(api.ModelDomainError, match=needle.replace("[", r"\[").replace("]", r"\]")):
        api.load_risk(rdir)


def test_registry_errors_suggest_only_loadable_names(cl, mlflow_uri):
    """A bare ``--model champion`` for ``fuse`` suggested registration models, which
    then failed after downloading 112 files."""
    from _registry_models import log_linear

    from traffictwin.mlops import registry as reg

    mv = reg.ensure_version(cl, "traffictwin-registration", log_linear(1.0))
    cl.set_registered_model_alias("traffictwin-registration", "champion", mv.version)
    with pytest.raises(api.ApiError, match="no fusion model is registered yet") as exc:
        api.load_fusion("champion", tracking_uri=mlflow_uri)
    assert "traffictwin-registration" not in str(exc.value)
    with pytest.raises(
        api.ApiError, match="is not a fusion model; fusion models are registered as"
    ):
        api.load_fusion("traffictwin-registration@champion", tracking_uri=mlflow_uri)
    reg.ensure_version(cl, "traffictwin-fusion-D", log_linear(2.0))  # a per-configuration name
    with pytest.raises(api.ApiError, match=r"registered fusion models: traffictwin-fusion-D\)"):
        api.load_fusion("champion", tracking_uri=mlflow_uri)


# ------------------------------------------------------------------ every argument, an ApiError


def _api_calls(fusion, rm):
    left, right = textured_pair()
    frame = api.Frame("a", left, right)
    return [
        (
            lambda: api.Frame("a", [1, 2], right),
            "frame 'a' left: expected an image path or a uint8 array, got list",
        ),
        (
            lambda: api.Frame("a", left, None),
            "frame 'a' right: expected an image path or a uint8 array, got NoneType",
        ),
        (lambda: api.Frame(7, left, right), "Frame id: expected a string, got int"),
        (lambda: api.read_image(123), "path: expected a file path (str or os.PathLike), got int"),
        (lambda: api.check_image_file(None), "path: expected a file path"),
        (lambda: api.frames_in_folder(3.5), "folder: expected a file path"),
        (lambda: api.load_masses(b"x.npz"), "path: expected a file path"),
        (
            lambda: api.load_fusion(None),
            "model: expected a registry reference name@alias or a model folder path",
        ),
        (lambda: api.load_risk(42), "model: expected a registry reference"),
        (lambda: api.load_risk("x", tracking_uri=5), "tracking_uri: expected a string or None"),
        (lambda: api.resolve_tracking_uri(b"sqlite:///x.db"), "tracking_uri: expected a string"),
        (lambda: api.connect(3), "tracking_uri: expected a string or None"),
        (
            lambda: api.fuse(fusion, [], batch_size=2.5),
            "batch_size: expected an integer >= 1, got 2.5",
        ),
        (
            lambda: api.fuse(fusion, [], batch_size=True),
            "batch_size: expected an integer >= 1, got True",
        ),
        (lambda: api.fuse(fusion, [], batch_size=0), "batch_size: must be >= 1, got 0"),
        (lambda: api.fuse(fusion, None), "pairs: expected an iterable of api.FusePair"),
        (lambda: list(api.fuse(fusion, [(1, 2, 3, 4)])), "pairs[0]: expected api.FusePair"),
        (lambda: api.fuse("model", []), "model: expected a FusionModel"),
        (lambda: api.FusePair(*np.zeros((4, 1)), id=3), "FusePair id: expected a string, got int"),
        (
            lambda: api.assess_risk(rm, [frame], speed=8.0, batch_size=1.5),
            "batch_size: expected an integer >= 1, got 1.5",
        ),
        (
            lambda: api.assess_risk(rm, [frame], speed=8.0, resize=1),
            "resize: expected True or False, got 1",
        ),
        (
            lambda: api.assess_risk(rm, [frame], speed=8.0, settings={}),
            "settings: expected api.StereoSettings or None, got dict",
        ),
        (
            lambda: api.assess_risk(rm, [frame], speed=8.0, thw_threshold=True),
            "thw_threshold: expected a number of seconds, got True",
        ),
        (
            lambda: api.assess_risk(rm, frame, speed=8.0),
            "frames: expected an iterable of api.Frame",
        ),
        (
            lambda: list(api.assess_risk(rm, [(left, right)], speed=8.0)),
            "frames[0]: expected api.Frame(id, left, right), got tuple",
        ),
        (lambda: api.assess_risk(None, [frame]), "risk: expected a LoadedRisk"),
        (
            lambda: api.assess_risk(rm, [frame], speed=True),
            "speed: expected a number of m/s, got bool",
        ),
        (
            lambda: api.StereoSettings({"nope": 1}, {}, "x"),
            "StereoSettings.sgm: unknown setting 'nope'",
        ),
        (
            lambda: api.StereoSettings({}, {"min_dx": "1"}, "x"),
            "StereoSettings.orb: setting 'min_dx' = '1' is not a float",
        ),
        (
            lambda: api.StereoSettings({}, [], "x"),
            "StereoSettings.orb: expected a mapping of settings, got list",
        ),
        (lambda: api.stereo_settings(None, 5), "params_path: expected a file path"),
        (lambda: api.speed_range("risk"), "risk: expected a LoadedRisk"),
        (lambda: api.check_speed(rm, 8.0, params_path=[]), "params_path: expected a file path"),
        (
            lambda: api.decision_cut(rm, False),
            "thw_threshold: expected a number of seconds, got False",
        ),
        (lambda: api.risk_verdict(True, None), "risk: expected a number in [0, 1], got True"),
        (lambda: api.risk_verdict(0.5, None, cut="0.3"), "cut: expected a risk in [0, 1] or None"),
        (
            lambda: api.check_fusion_domain(None, (32, 48), 0.5, "x"),
            "model: expected a FusionModel",
        ),
    ]


def test_every_public_api_function_raises_its_own_errors(fusion, risk_dir):
    rm = api.load_risk(risk_dir)
    for call, needle in _api_calls(fusion, rm):
        with pytest.raises(api.InputValueError) as exc:
            call()
        assert needle in str(exc.value), (needle, str(exc.value))


def test_assess_risk_batch_size_is_never_rounded_into_buffering_the_stream(risk_dir):
    rm = api.load_risk(risk_dir)
    left, right = textured_pair()
    taken = []

    def frames():
        for k in range(3):
            taken.append(k)
            yield api.Frame(str(k), left, right)

    with pytest.raises(api.InputValueError, match="batch_size"):
        api.assess_risk(rm, frames(), speed=8.0, batch_size=1.5)
    assert taken == []  # refused at the call, before a frame is read
    rows = api.assess_risk(rm, frames(), speed=8.0, batch_size=1)
    next(rows)
    assert taken == [0]  # one frame per batch: the stream is not buffered
