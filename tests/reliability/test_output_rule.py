"""One output rule: ``--force`` replaces only a previous output of the command's own kind,
recognised by content, and never a repository's code, configuration, tests or DVC outputs, a
link, device or FIFO; two writers of one new output: one wins; FIFOs as inputs are refused at
once; odd output names are one line. Every case checks the one message line, the exit status
and that the target is unchanged afterwards."""

from __future__ import annotations

import contextlib
import hashlib
import io
import os
import subprocess
import sys
from pathlib import Path

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

from traffictwin import cli
from traffictwin.io.outputs import OutputError, OutputSet, check_regular_file, mark_png

ROOT = Path(__file__).resolve().parents[2]
RUNS_HEADER = "run_name,run_id,status,start_time\nr,abc,FINISHED,2026-01-01\n"
TIMEOUT = 120  # s: a FIFO opened by mistake would block forever; the subprocess is bounded


@pytest.fixture(scope="module")
def fusion_dir(tmp_path_factory) -> Path:
    return save_fusion_model(tmp_path_factory.mktemp("fusion") / "m")


@pytest.fixture(scope="module")
def risk_dir(tmp_path_factory) -> Path:
    return save_risk(tmp_path_factory.mktemp("risk") / "m")


@pytest.fixture
def maps(tmp_path) -> tuple[Path, Path]:
    return (
        save_map(tmp_path / "a.npz", *masses(1), cell=np.float64(CELL)),
        save_map(tmp_path / "b.npz", *masses(2)),
    )


def _sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def _one_line(err: str, *needles: str) -> str:
    lines = [ln for ln in err.strip().splitlines() if ln]
    assert len(lines) == 1, err
    for n in needles:
        assert n in lines[0], lines[0]
    return lines[0]


def _cli(*argv: str) -> subprocess.CompletedProcess:
    """``traffictwin ARGV`` in this process (:func:`traffictwin.cli.main`): its exit code and what
    it wrote to stderr (a special file that blocked would hit the reliability tests' time limit)."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        rc = cli.main(list(argv))
    return subprocess.CompletedProcess(list(argv), rc, "", err.getvalue())


# ------------------------------------------------------------------ a repository's own files


@pytest.fixture
def repo(tmp_path) -> Path:
    """A repository: code, configuration, tests, a DVC pipeline with plain, templated and
    metrics outputs and a ``.dvc``-tracked folder; every file looks like a previous runs table."""
    r = tmp_path / "repo"
    (r / ".git").mkdir(parents=True)
    (r / "dvc.yaml").write_text(
        "stages:\n"
        "  evaluate:\n"
        "    cmd: x\n"
        "    outs:\n"
        "      - reports/metrics/risk.csv: {cache: false}\n"
        "      - data/out\n"
        "  train:\n"
        "    foreach: [a, b]\n"
        "    do:\n"
        "      cmd: y\n"
        '      outs: ["models/${item}/table.csv"]\n'
        '      metrics: ["reports/m_${item}.csv"]\n'
    )
    (r / "raw.dvc").write_text("outs:\n- path: raw\n")
    for rel in (
        "src/traffictwin/table.csv",
        "conf/table.csv",
        "tests/table.csv",
        "reports/metrics/risk.csv",
        "data/out/shard.csv",
        "models/a/table.csv",
        "reports/m_b.csv",
        "raw/x.csv",
    ):
        (r / rel).parent.mkdir(parents=True, exist_ok=True)
        (r / rel).write_text(RUNS_HEADER)
    return r


@pytest.mark.parametrize(
    ("rel", "why"),
    [
        ("src/traffictwin/table.csv", "under src/ of the repository"),
        ("conf/table.csv", "under conf/ of the repository"),
        ("tests/table.csv", "under tests/ of the repository"),
        ("reports/metrics/risk.csv", "an output of the DVC pipeline"),
        ("data/out/shard.csv", "an output of the DVC pipeline"),
        ("models/a/table.csv", "an output of the DVC pipeline"),
        ("reports/m_b.csv", "an output of the DVC pipeline"),
        ("raw/x.csv", "tracked by DVC"),
        ("reports/metrics/new.csv", None),
    ],
)
def test_force_never_replaces_repository_files_or_dvc_outputs(repo, rel, why, capsys):
    """Even a file whose content is a previous ``runs compare`` table is refused where it is
    the repository's code, configuration, tests or a DVC output (path not yet there: refused
    too); the message names the reason and never offers --force."""
    target = repo / rel
    before = _sha(target) if target.exists() else None
    argv = ["runs", "compare", "--experiment", "x", "--tracking-uri", "sqlite:////nonexistent/db"]
    rc = cli.main([*argv, "--csv", str(target), "--force"])
    err = capsys.readouterr().err
    if why is None:  # a free path of the repository: the command goes on (to the missing registry)
        assert "refusing to write" not in err and not target.exists()
        return
    assert rc == 1
    line = _one_line(err, "--csv", "refusing to write", str(target), why)
    assert "--force" not in line
    assert _sha(target) == before


def test_risk_result_onto_the_package_source_is_refused(tmp_path, risk_dir, capsys):
    """``risk … -o src/traffictwin/__init__.py --force`` of a checkout: refused, file unchanged."""
    r = tmp_path / "checkout"
    (r / ".git").mkdir(parents=True)
    init = r / "src" / "traffictwin" / "__init__.py"
    init.parent.mkdir(parents=True)
    init.write_text('__version__ = "1"\n')
    lp, rp = write_pair(tmp_path / "in", "f", *textured_pair())
    before = _sha(init)
    rc = cli.main(["risk", str(lp), str(rp), "--model", str(risk_dir), "-o", str(init), "--force"])
    assert rc == 1
    _one_line(capsys.readouterr().err, "refusing to write", "under src/")
    assert _sha(init) == before


def test_project_outputs_are_refused_in_this_repository():
    """The project's own examples: its DVC metrics and sources are no output of any command."""
    for rel in ("reports/metrics/risk.json", "src/traffictwin/__init__.py", "conf/config.yaml"):
        with pytest.raises(OutputError, match="refusing to write"):
            OutputSet([ROOT / rel], force=True)


# ------------------------------------------------------------------ kind, by content


def test_export_never_replaces_a_grid_map_and_fuse_never_an_export(
    tmp_path, maps, fusion_dir, capsys
):
    m1 = maps[0]
    before = _sha(m1)
    # export onto a grid map (an input map, no 'u'): refused with --force
    rc = cli.main(["export", "fusion", "--model", str(fusion_dir), "-o", str(m1), "--force"])
    assert rc == 1
    line = _one_line(capsys.readouterr().err, "a.npz exists and is not a previous .npz output")
    assert "TorchScript" in line and "--force" not in line
    assert _sha(m1) == before
    # export onto a previous fuse output: still not its kind
    assert cli.main(fuse_args(*maps, fusion_dir, tmp_path / "fused")) == 0
    fused = tmp_path / "fused.npz"
    before = _sha(fused)
    rc = cli.main(["export", "fusion", "--model", str(fusion_dir), "-o", str(fused), "--force"])
    assert rc == 1
    _one_line(capsys.readouterr().err, "is not a previous .npz output")
    assert _sha(fused) == before
    # a previous export named .npz is no grid: fuse --force refuses it
    exp = tmp_path / "model.npz"
    assert cli.main(["export", "fusion", "--model", str(fusion_dir), "-o", str(exp)]) == 0
    capsys.readouterr()
    before = _sha(exp)
    assert cli.main([*fuse_args(*maps, fusion_dir, tmp_path / "model"), "--force"]) == 1
    _one_line(capsys.readouterr().err, "model.npz exists and is not a previous .npz output")
    assert _sha(exp) == before
    # its own kind: "pass --force", then replaced
    assert cli.main(["export", "fusion", "--model", str(fusion_dir), "-o", str(exp)]) == 1
    _one_line(capsys.readouterr().err, "model.npz exists (a TorchScript file", "pass --force")
    rc = cli.main(["export", "fusion", "--model", str(fusion_dir), "-o", str(exp), "--force"])
    assert rc == 0


def test_a_preview_is_recognised_by_its_marker(tmp_path):
    """A marked PNG still decodes; ``--force`` replaces it, and not the same PNG unmarked."""
    import cv2

    ok, png = cv2.imencode(".png", np.zeros((3, 5, 3), np.uint8))
    marked = mark_png(png.tobytes())
    img = cv2.imdecode(np.frombuffer(marked, np.uint8), cv2.IMREAD_COLOR)
    assert ok and img is not None and img.shape == (3, 5, 3)
    (tmp_path / "ours.png").write_bytes(marked)
    (tmp_path / "theirs.png").write_bytes(png.tobytes())
    OutputSet([tmp_path / "ours.png"], force=True)
    with pytest.raises(OutputError, match="not a previous .png output"):
        OutputSet([tmp_path / "theirs.png"], force=True)


# ------------------------------------------------------------------ links, devices, FIFOs


def test_special_files_as_output_are_refused_without_offering_force(tmp_path):
    fifo = tmp_path / "t.csv"
    os.mkfifo(fifo)
    link = tmp_path / "out.csv"
    link.symlink_to("/proc/self/fd/1")
    base = ["runs", "compare", "--experiment", "x", "--tracking-uri", "sqlite:////nonexistent/db"]
    for target, what in (
        (fifo, "a FIFO"),
        (link, "a symbolic link"),
        ("/dev/null", "a character device"),
    ):
        for extra in ([], ["--force"]):
            res = _cli(*base, "--csv", str(target), *extra)
            assert res.returncode == 1, res
            line = _one_line(res.stderr, f"it is {what}", "choose another path")
            assert "--force" not in line.split("error:", 1)[1]
    assert fifo.is_fifo() and link.is_symlink() and Path("/dev/null").is_char_device()


def test_fifo_model_files_and_params_are_refused_at_once(tmp_path, risk_dir):
    """``model_meta.json`` / ``model.ckpt`` / ``--params`` FIFOs: one line, no blocking."""
    lp, rp = write_pair(tmp_path / "in", "f", *textured_pair())
    for name in ("model_meta.json", "model.ckpt"):
        m = tmp_path / f"m_{name}"
        m.mkdir()
        for f in ("model_meta.json", "model.ckpt"):
            if f == name:
                os.mkfifo(m / f)
            else:
                (m / f).write_bytes((risk_dir / f).read_bytes())
        res = _cli("risk", str(lp), str(rp), "--model", str(m))
        assert res.returncode == 1, res
        _one_line(res.stderr, name, "FIFO")
    fifo = tmp_path / "params.yaml"
    os.mkfifo(fifo)
    res = _cli("risk", str(lp), str(rp), "--model", str(risk_dir), "--params", str(fifo))
    assert res.returncode == 1, res
    line = _one_line(res.stderr, "--params", "FIFO")
    assert "not found" not in line


def test_check_regular_file_says_what_the_path_is(tmp_path):
    os.mkfifo(tmp_path / "p")
    with pytest.raises(OSError, match="is a FIFO") as exc:
        check_regular_file(tmp_path / "p", "a log file")
    assert exc.value.filename == str(tmp_path / "p") and "expected a log file" in str(exc.value)
    with pytest.raises(FileNotFoundError):
        check_regular_file(tmp_path / "missing")
    (tmp_path / "f").write_text("x")
    assert check_regular_file(tmp_path / "f") == tmp_path / "f"


# ------------------------------------------------------------------ two writers


def test_two_writers_of_one_new_output_one_wins(tmp_path):
    """Both checked while the names were free; the first commit wins, the second fails with one
    line and leaves the winner's files and no temp file."""
    names = [tmp_path / "race.npz", tmp_path / "race.png"]
    a = OutputSet(names)
    b = OutputSet(names)
    for s, tag in ((a, b"A"), (b, b"B")):
        for p in names:
            s.write_bytes(p, tag)
    with a:
        a.commit()
    with pytest.raises(OutputError, match="created by another command while this one ran") as exc:
        with b:
            b.commit()
    _one_line(str(exc.value), "race.npz")
    assert [p.read_bytes() for p in names] == [b"A", b"A"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["race.npz", "race.png"]


def test_two_fuse_commands_onto_one_new_output_one_wins(tmp_path, maps, fusion_dir):
    """``fuse -o race`` twice at once, without ``--force``: whatever the timing (both checked
    while the name was free, or the second after the first committed), one exits 0 and the other
    1 with one line naming the output; the winner's two files stay, no temp file."""
    argv = [[*fuse_args(*maps, fusion_dir, tmp_path / "race")] for _ in range(2)]
    argv[1][argv[1].index("--pose2") + 1] = "3.0,0.5,0.0"  # a different result
    env = {**os.environ, "PYTHONPATH": f"{ROOT / 'src'}{os.pathsep}{ROOT}"}
    procs = [
        subprocess.Popen(
            [sys.executable, "-m", "traffictwin.cli", *a],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )
        for a in argv
    ]
    results = []
    for p in procs:
        try:
            _, err = p.communicate(timeout=TIMEOUT)
        finally:
            if p.poll() is None:
                p.kill()
        results.append((p.returncode, err))
    assert sorted(rc for rc, _ in results) == [0, 1], results
    (err,) = [e for rc, e in results if rc == 1]
    line = _one_line(err, "race.")
    assert "exists" in line or "created by another command while this one ran" in line, line
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(("race", ".race"))) == [
        "race.npz",
        "race.png",
    ]
    with np.load(tmp_path / "race.npz") as z:
        assert np.isfinite(z["m_free"]).all()


def test_a_writer_that_loses_half_way_removes_what_it_made(tmp_path):
    """B made ``x.npz`` first, A ``x.png``: B fails on the PNG and takes its ``x.npz`` back."""
    npz, png = tmp_path / "x.npz", tmp_path / "x.png"
    b = OutputSet([npz, png])
    b.write_bytes(npz, b"B")
    b.write_bytes(png, b"B")
    png.write_bytes(b"A")  # another writer won this name
    with pytest.raises(OutputError, match="x.png was created by another command"):
        with b:
            b.commit()
    assert not npz.exists() and png.read_bytes() == b"A"


# ------------------------------------------------------------------ names


@pytest.mark.parametrize(("name", "needle"), [("", "empty"), ("sub/", "is a folder")])
def test_empty_or_folder_output_names_are_one_line(
    tmp_path, maps, fusion_dir, name, needle, capsys
):
    (tmp_path / "sub").mkdir()
    out = name if name == "" else str(tmp_path / name)
    assert cli.main(fuse_args(*maps, fusion_dir, out)) == 1
    _one_line(capsys.readouterr().err, "-o", needle)
    assert not (tmp_path / "sub.npz").exists() and not list((tmp_path / "sub").iterdir())
    assert cli.main(fuse_args(*maps, fusion_dir, tmp_path / "sub")) == 1  # an existing folder
    _one_line(capsys.readouterr().err, "is a folder")
    assert not (tmp_path / "sub.npz").exists()


def test_pair_list_with_a_byte_order_mark(tmp_path, maps, fusion_dir, capsys):
    lst = tmp_path / "pairs.csv"
    lst.write_bytes(
        "\ufeffid,map1,map2,x1,y1,yaw1,x2,y2,yaw2\np,a.npz,b.npz,1,2,0.1,4,1,-0.05\n".encode()
    )
    rc = cli.main(
        ["fuse", "--pairs", str(lst), "--model", str(fusion_dir), "-o", str(tmp_path / "o")]
    )
    assert rc == 0, capsys.readouterr().err
    assert (tmp_path / "o" / "p.npz").is_file() and (tmp_path / "o" / "summary.csv").is_file()


def test_an_empty_output_name_is_one_line_for_every_command(tmp_path, fusion_dir, risk_dir, capsys):
    """``-o ""`` / ``--csv ""``: one line naming the option, never stdout or the current folder."""
    lp, rp = write_pair(tmp_path / "in", "f", *textured_pair())
    for argv in (
        ["export", "fusion", "--model", str(fusion_dir), "-o", ""],
        ["runs", "compare", "--experiment", "x", "--csv", ""],
        ["risk", str(lp), str(rp), "--model", str(risk_dir), "-o", ""],
    ):
        assert cli.main(argv) == 1
        _one_line(capsys.readouterr().err, "the output path is empty")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in"]


def test_a_link_to_the_mlflow_store_is_still_the_store(tmp_path):
    """``protected_reason`` (shared with the registry commands' log checks) follows a link."""
    import sqlite3

    from traffictwin.io.outputs import protected_reason

    con = sqlite3.connect(tmp_path / "mlflow.db")
    con.execute("create table t (a)")
    con.commit()
    con.close()
    (tmp_path / "log.jsonl").symlink_to(tmp_path / "mlflow.db")
    assert "SQLite database" in protected_reason(tmp_path / "log.jsonl")
