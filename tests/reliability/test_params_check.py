"""Experiments that lose nothing: ``pipelines.check_params`` validates the whole of params.yaml
with the stages' own checks before DVC removes any stage's outputs, a rejected value is not left
in params.yaml (the last accepted file is put back, the rejected one kept aside), and sizes that
allocate are bounded in the config schema.

Before: ``dvc exp run -S profile=ci -S fusion_model.train.batch_size=-3 train_fusion`` printed the
right one-line error, but only after DVC had removed ``models/fusion/network`` and
``reports/metrics/train_fusion_network.json`` (a ``cache: false`` output cannot be checked out
again), and params.yaml kept the rejected value; ``-S grid.rows=4096 -S grid.cols=4096 generate_fusion`` ran 86 s into ``std::bad_alloc``.
"""

from __future__ import annotations

import copy
import hashlib
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from conftest import committed, composed

from pipelines import check_params
from pipelines._common import run_stage
from traffictwin.config import ConfigError

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def good() -> dict:
    return yaml.safe_load(committed("params.yaml"))


def _with(params: dict, dotted: str, value) -> dict:
    out = copy.deepcopy(params)
    node = out
    *head, last = dotted.split(".")
    for k in head:
        node = node[k]
    node[last] = value
    return out


def test_every_profile_passes_every_check(good) -> None:
    assert check_params.check(good) == [name for name, _ in check_params.CHECKS]
    for profile in ("ci", "paper"):  # paper: ResNet-50, 256 x 176, 10,000 pairs, 110k frames
        check_params.check(composed(f"profile={profile}"))


@pytest.mark.parametrize(
    ("key", "value", "named"),
    [
        (
            "fusion_model.train.batch_size",
            -3,
            "'fusion_model.train.batch_size' must be >= 2, got -3",
        ),
        ("grid.rows", 4096, "'grid.rows' must be <= 1024, got 4096"),
        ("grid.cols", 4096, "'grid.cols' must be <= 1024, got 4096"),
        ("fusion_data.scenarios", 10**9, "'fusion_data.scenarios' must be <= 100000"),
        ("fusion_data.encounters_per_scenario", 10**6, "'fusion_data.encounters_per_scenario'"),
        ("risk_data.camera.width", 100_000, "'risk_data.camera.width' must be <= 4096"),
        ("risk_data.frames_per_sequence", 10**6, "'risk_data.frames_per_sequence' must be <="),
        ("twin.frames", 10**6, "'twin.frames' must be <= 10000"),
        ("risk_data.sgm.num_disparities", 512, "'risk_data.sgm': num_disparities=512"),
        ("fusion_model.optim.lr", float("inf"), "'fusion_model.optim.lr' must be a finite number"),
        ("fusion_model.architecture.backbone.base_width", 4096, "base_width"),
        ("fusion_model.loss.name", "l1", "'fusion_model.loss.name' must be one of"),
    ],
)
def test_a_rejected_value_names_its_key_and_bound(good, key, value, named) -> None:
    with pytest.raises(ConfigError) as info:
        check_params.check(_with(good, key, value))
    line = str(info.value)
    assert "\n" not in line and named in line, line
    assert str(value) in line.replace(",", "") or key.endswith("lr"), line


def test_a_variant_loss_is_a_registered_loss(good) -> None:
    variant = {"x": {"config": "mixed", "inputs": "prealigned", "loss": "l1"}}
    with pytest.raises(ConfigError, match=r"'fusion_variants.x.loss': unknown fusion loss 'l1'"):
        check_params.check(_with(good, "fusion_variants", variant))


#: the two forms of dvc.lock's record of the accepted params.yaml: the md5 of the stage's
#: ``params.yaml`` file dependency, and (locks of earlier commits) every key as params
RECORDS = ("md5", "values")


def _lock(accepted: str, record: str = "md5") -> str:
    """dvc.lock text whose check_params stage records the params.yaml ``accepted`` as DVC 3
    writes it: a ``params.yaml`` dep (``record="md5"``: path, hash, md5, size, after a code
    dep) or every key as params (``"values"``, floats as DVC writes them: ``1e-07``, no dot)."""
    stage: dict = {"cmd": "python -m pipelines.check_params"}
    if record == "md5":
        data = accepted.encode()
        code = {"path": "pipelines/check_params.py", "hash": "md5", "md5": "0" * 32, "size": 1}
        dep = {"path": "params.yaml", "hash": "md5", "md5": hashlib.md5(data).hexdigest()}
        stage["deps"] = [code, {**dep, "size": len(data)}]
    else:
        stage["params"] = {"params.yaml": yaml.safe_load(accepted)}
    stage["outs"] = [{"path": "data/params_ok.json", "hash": "md5", "md5": "1" * 32, "size": 53}]
    lock = yaml.safe_dump({"schema": "2.0", "stages": {"check_params": stage}}, sort_keys=False)
    return re.sub(r"(\d)\.0e", r"\1e", lock)


def _root(tmp_path: Path, text: str, accepted: str | None = None, record: str = "md5") -> Path:
    """A repository root with ``params.yaml`` = ``text`` and a dvc.lock whose check_params
    record is of the params.yaml ``accepted`` (:func:`_lock`)."""
    root = tmp_path / "root"
    root.mkdir(exist_ok=True)
    (root / "params.yaml").write_text(text)
    if accepted is not None:
        (root / "dvc.lock").write_text(_lock(accepted, record))
    return root


def _dump(params: dict) -> str:
    return yaml.safe_dump(params, sort_keys=False)


def test_the_output_does_not_change_with_the_parameters(good, tmp_path) -> None:
    out = tmp_path / "params_ok.json"
    written = []
    for params in (good, _with(good, "fusion_model.optim.lr", 0.123), _with(good, "seed", 7)):
        check_params.main([], output=out, root=_root(tmp_path, _dump(params)))
        written.append(out.read_bytes())
    assert written[0] == written[1] == written[2]
    assert json.loads(written[0]) == {
        "params": "params.yaml",
        "schema_version": check_params.SCHEMA_VERSION,
    }


def _rejected(root: Path, out: Path, monkeypatch, capsys) -> str:
    """Run the stage on ``root``: exit 2, one stderr line (returned), no output written."""
    monkeypatch.delenv("TRAFFICTWIN_TRACEBACK", raising=False)
    with pytest.raises(SystemExit) as info:
        run_stage(lambda: check_params.main([], output=out, root=root), "check_params")
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("check_params: error: ConfigError: "), err
    assert not out.exists()
    return err.strip()


@pytest.mark.parametrize("record", RECORDS)
def test_a_rejected_value_is_one_line_exit_2_and_params_yaml_restored(
    good, tmp_path, monkeypatch, capsys, record
) -> None:
    """The accepted file (kept by the last successful check, dvc.lock records its md5, or its
    values in an older lock) is put back byte for byte; the rejected one is kept, never lost."""
    accepted = committed("params.yaml")  # with its header comment: restored byte for byte
    root = _root(tmp_path, accepted, accepted, record)
    check_params.main([], output=tmp_path / "first.json", root=root)
    bad = _dump(_with(good, "fusion_model.train.batch_size", -3))
    (root / "params.yaml").write_text(bad)
    out = tmp_path / "params_ok.json"
    line = _rejected(root, out, monkeypatch, capsys)
    assert "'fusion_model.train.batch_size' must be >= 2, got -3" in line
    assert "params.yaml restored to the parameters the last check accepted" in line
    assert (root / "params.yaml").read_text() == accepted
    assert (root / check_params.KEPT / "rejected.yaml").read_text() == bad
    # the restored file passes: the next run writes the output again
    check_params.main([], output=out, root=root)
    assert out.is_file()


@pytest.mark.parametrize("record", RECORDS)
def test_a_stale_kept_copy_is_never_restored(good, tmp_path, monkeypatch, capsys, record) -> None:
    """dvc.lock's record decides: after a checkout of other parameters the copy kept from before
    is not theirs, and without git there is no other source: params.yaml stays, and says so."""
    root = _root(tmp_path, _dump(good), _dump(good), record)
    check_params.main([], output=tmp_path / "first.json", root=root)  # keeps the seed-20... copy
    other = _dump(_with(good, "seed", 7))
    (root / "dvc.lock").unlink()
    root = _root(tmp_path, other, other, record)  # a checkout: other params, their lock
    bad = _dump(_with(yaml.safe_load(other), "grid.rows", 4096))
    (root / "params.yaml").write_text(bad)
    line = _rejected(root, tmp_path / "o.json", monkeypatch, capsys)
    assert "'grid.rows' must be <= 1024, got 4096" in line
    assert "params.yaml keeps the rejected value" in line and "git checkout params.yaml" in line
    assert (root / "params.yaml").read_text() == bad
    assert not (root / check_params.KEPT / "rejected.yaml").exists()


def test_without_a_lock_record_params_yaml_is_left_and_the_line_says_so(
    good, tmp_path, monkeypatch, capsys
) -> None:
    bad = _dump(_with(good, "fusion_model.train.batch_size", -3))
    root = _root(tmp_path, bad)
    line = _rejected(root, tmp_path / "o.json", monkeypatch, capsys)
    assert "params.yaml keeps the rejected value (no accepted parameters in dvc.lock" in line
    assert (root / "params.yaml").read_text() == bad


@pytest.mark.parametrize("record", RECORDS)
def test_the_committed_file_is_restored_when_it_is_the_accepted_one(
    good, tmp_path, monkeypatch, capsys, record
) -> None:
    """No kept copy (a fresh clone): the committed params.yaml is restored when dvc.lock's record
    is of it; a kept copy of other parameters is passed over."""
    accepted = committed("params.yaml")
    root = _root(tmp_path, accepted, accepted, record)
    git = ["git", "-c", "user.email=t@t", "-c", "user.name=t", "-c", "commit.gpgsign=false"]
    for cmd in ([*git, "init", "-q"], [*git, "add", "params.yaml"], [*git, "commit", "-qm", "p"]):
        subprocess.run(cmd, cwd=root, check=True, capture_output=True, timeout=60)
    stale = _dump(_with(good, "seed", 7))
    (root / check_params.KEPT).mkdir(parents=True)
    (root / check_params.KEPT / "accepted.yaml").write_text(stale)
    bad = _dump(_with(good, "twin.frames", 10**6))
    (root / "params.yaml").write_text(bad)
    line = _rejected(root, tmp_path / "o.json", monkeypatch, capsys)
    assert "params.yaml restored to the parameters the last check accepted" in line, line
    assert (root / "params.yaml").read_text() == accepted
    assert (root / check_params.KEPT / "rejected.yaml").read_text() == bad
    assert (root / check_params.KEPT / "accepted.yaml").read_text() == stale


@pytest.mark.parametrize("record", RECORDS)
def test_an_accepted_file_that_fails_now_is_left_and_the_line_says_so(
    good, tmp_path, monkeypatch, capsys, record
) -> None:
    """A file dvc.lock records as accepted that the (newer) checks reject: nothing to put back."""
    bad = _dump(_with(good, "grid.rows", 4096))
    root = _root(tmp_path, bad, bad, record)
    line = _rejected(root, tmp_path / "o.json", monkeypatch, capsys)
    assert "params.yaml is unchanged since the last accepted check" in line, line
    assert (root / "params.yaml").read_text() == bad
    assert not (root / check_params.KEPT / "rejected.yaml").exists()


def test_the_lock_record_is_the_md5_of_the_params_yaml_dep(good, tmp_path) -> None:
    """The md5 record wins over an old values record, matches bytes (not values), and a DVC 2
    record (no ``hash: md5``) hashes CRLF line ends as LF, as DVC does."""
    text = _dump(good)
    root = _root(tmp_path, text, text)
    accepted = check_params.accepted_params(root)
    assert accepted == check_params.Accepted(md5=hashlib.md5(text.encode()).hexdigest())
    assert accepted.holds(text.encode())
    assert not accepted.holds(text.encode() + b"# a comment\n")  # same values, other bytes
    lock = yaml.safe_load(_lock(text))
    lock["stages"]["check_params"]["params"] = {"params.yaml": _with(good, "seed", 7)}
    (root / "dvc.lock").write_text(yaml.safe_dump(lock))
    assert check_params.accepted_params(root) == accepted
    del lock["stages"]["check_params"]["deps"][1]["hash"]  # as DVC 2 wrote it
    (root / "dvc.lock").write_text(yaml.safe_dump(lock))
    legacy = check_params.accepted_params(root)
    assert legacy is not None and legacy.dos2unix
    assert legacy.holds(text.replace("\n", "\r\n").encode())
    assert not accepted.holds(text.replace("\n", "\r\n").encode())
    del lock["stages"]["check_params"]["deps"]  # only the old values record left
    (root / "dvc.lock").write_text(yaml.safe_dump(lock))
    old = check_params.accepted_params(root)
    assert old == check_params.Accepted(values=_with(good, "seed", 7))
    assert old.holds(_dump(_with(good, "seed", 7)).encode()) and not old.holds(text.encode())
    del lock["stages"]["check_params"]["params"]
    (root / "dvc.lock").write_text(yaml.safe_dump(lock))
    assert check_params.accepted_params(root) is None


def test_check_params_and_report_depend_on_params_yaml_as_a_file() -> None:
    """The two stages that read all of params.yaml list it as one file dependency (four lines
    of dvc.lock), never as params of every key (all of params.yaml, once per stage)."""
    stages = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]
    for name in ("check_params", "report"):
        assert "params.yaml" in stages[name]["deps"], name
        assert "params.yaml" not in stages[name].get("params", []), name
        assert {"params.yaml": None} not in stages[name].get("params", []), name


def test_dvc_lock_floats_read_as_params_yaml_floats() -> None:
    """DVC writes ``1e-07`` (YAML 1.2); PyYAML alone would read a string and never match."""
    assert yaml.safe_load("a: 1e-07")["a"] == "1e-07"
    assert check_params._load("a: 1e-07\nb: 1.0e-07\nc: '1e-07'\nd: 3") == {
        "a": 1e-07,
        "b": 1e-07,
        "c": "1e-07",
        "d": 3,
    }


# ---------------------------------------------------------------------------------------------
# the DVC behaviour the stage relies on (DVC 3): a failing first stage keeps the others' outputs;
# an unchanged output re-runs nothing downstream; what `dvc exp run` does with params.yaml


def _dvc_repo(dest: Path) -> Path:
    """A tiny git + DVC repo: ``check`` (the real check_params stage run on this repo's
    params.yaml) and ``down``, which depends on its output and one parameter."""
    dest.mkdir()
    (dest / "params.yaml").write_text(committed("params.yaml"))
    (dest / "down.py").write_text(
        "import yaml\n"
        "p = yaml.safe_load(open('params.yaml'))\n"
        "open('down.txt', 'w').write(str(p['fusion_model']['train']['batch_size']))\n"
        "open('runs.log', 'a').write('down\\n')\n"
    )
    shutil.copytree(ROOT / "conf", dest / "conf")  # for DVC's Hydra composition (exp run -S)
    check = (
        "from pathlib import Path; import pipelines.check_params as c; "
        "from pipelines._common import run_stage; "
        "run_stage(lambda: c.main([], output=Path('params_ok.json'), root=Path.cwd()), "
        "'check_params')"
    )
    (dest / "dvc.yaml").write_text(
        yaml.safe_dump(
            {
                "stages": {
                    "check_params": {
                        "cmd": f'{sys.executable} -c "{check}"',
                        "deps": ["params.yaml"],  # the whole file, as the real stage
                        "outs": ["params_ok.json"],
                    },
                    "down": {
                        "cmd": f"{sys.executable} down.py",
                        "deps": ["down.py", "params_ok.json"],
                        "params": ["fusion_model.train.batch_size"],
                        "outs": [{"down.txt": {"cache": False}}],
                    },
                }
            }
        )
    )
    (dest / ".gitignore").write_text("runs.log\n/.cache/\n")
    env = {
        "PYTHONPATH": f"{ROOT / 'src'}:{ROOT}",
        "PATH": f"{Path(sys.executable).parent}:/usr/bin:/bin",
    }
    git = ["git", "-c", "user.email=t@t", "-c", "user.name=t", "-c", "commit.gpgsign=false"]
    for cmd in (
        [*git, "init", "-q"],
        ["dvc", "init", "-q"],
        ["dvc", "config", "hydra.enabled", "true"],
        ["dvc", "repro", "-q"],
        [*git, "add", "-A"],
        [*git, "commit", "-q", "-m", "start"],
    ):
        subprocess.run(cmd, cwd=dest, env=env, check=True, capture_output=True, timeout=300)
    return dest


def _dvc(repo: Path, *args: str) -> subprocess.CompletedProcess:
    env = {
        "PYTHONPATH": f"{ROOT / 'src'}:{ROOT}",
        "PATH": f"{Path(sys.executable).parent}:/usr/bin:/bin",
    }
    return subprocess.run(
        ["dvc", *args], cwd=repo, env=env, capture_output=True, text=True, timeout=300
    )


def _git_status(repo: Path) -> str:
    return subprocess.run(
        ["git", "status", "--porcelain"], cwd=repo, capture_output=True, text=True, timeout=60
    ).stdout


@pytest.mark.slow  # four dvc runs of the real check (~1.5 min on 2 cores)
def test_dvc_stops_at_the_check_and_keeps_every_other_output(tmp_path) -> None:
    repo = _dvc_repo(tmp_path / "repo")
    accepted = check_params.accepted_params(repo)  # DVC's own lock record: the file's md5
    assert accepted is not None and accepted.md5 is not None and not accepted.dos2unix
    before = (repo / "down.txt").read_text()
    good = (repo / "params.yaml").read_text()
    params = yaml.safe_load(good)
    # (a) `dvc exp run -S` of a rejected value (DVC composes conf/ and writes params.yaml before
    # any stage runs): the check fails, `down` keeps its output (a cache: false output), and
    # params.yaml is the accepted file again: the workspace is as before
    proc = _dvc(repo, "exp", "run", "-S", "fusion_model.train.batch_size=-3", "down")
    assert proc.returncode != 0
    out = proc.stderr + proc.stdout
    assert "check_params: error: ConfigError: params.yaml: 'fusion_model.train.batch_size'" in out
    assert "params.yaml restored to the parameters the last check accepted" in out
    assert (repo / "params.yaml").read_text() == good
    assert _git_status(repo) == ""
    assert (repo / "down.txt").read_text() == before
    assert (repo / "runs.log").read_text() == "down\n"
    # (b) the same value written by hand, then `dvc repro`: the same, the edit kept aside
    bad = yaml.safe_dump(_with(params, "fusion_model.train.batch_size", -3), sort_keys=False)
    (repo / "params.yaml").write_text(bad)
    proc = _dvc(repo, "repro", "down")
    assert proc.returncode != 0 and "params.yaml restored" in proc.stderr + proc.stdout
    assert (repo / "params.yaml").read_text() == good
    assert (repo / ".cache/traffictwin/params/rejected.yaml").read_text() == bad
    assert (repo / "down.txt").read_text() == before
    assert (repo / "runs.log").read_text() == "down\n"
    # (c) a valid value that `down` does not read: the check re-runs, writes the same output,
    # and `down` is not re-run
    (repo / "params.yaml").write_text(good.replace("seed: ", "seed: 1", 1))
    proc = _dvc(repo, "repro", "down")
    assert proc.returncode == 0, proc.stderr
    assert "Stage 'down' didn't change, skipping" in proc.stdout, proc.stdout
    assert (repo / "runs.log").read_text() == "down\n"
