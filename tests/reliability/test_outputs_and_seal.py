"""No command writes into a model folder, the MLflow store or a DVC
file (``--force`` or not), ``--force`` replaces only a previous output of the same kind, and a
model folder's seal (checkpoint hash + the metadata the loader trusts) cannot be peeled off."""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

import pytest
from _cli_models import fuse_args, masses, save_fusion_model, save_map, save_risk, textured_pair
from _cli_models import write_pair as write_stereo_pair

from traffictwin import api, cli
from traffictwin.fusion.model_io import FusionModelError, load_fusion_model
from traffictwin.io.outputs import OutputError, OutputSet, protected_reason
from traffictwin.risk.model_io import RiskModelError, load_risk_model

DOMAIN = {"speed_range": [0.0, 20.0], "max_speed": 20.0}


def _listing(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def _error_line(capsys, *needles: str) -> str:
    err = capsys.readouterr().err
    lines = [ln for ln in err.strip().splitlines() if ln]
    assert len(lines) == 1, err
    for n in needles:
        assert n in lines[0], lines[0]
    return lines[0]


@pytest.fixture()
def fusion_dir(tmp_path) -> Path:
    return save_fusion_model(tmp_path / "fusion_model")


@pytest.fixture()
def risk_dir(tmp_path) -> Path:
    return save_risk(tmp_path / "risk_model", {"label": "risk", "domain": DOMAIN})


@pytest.fixture()
def maps(tmp_path) -> tuple[Path, Path]:
    return save_map(tmp_path / "m1.npz", *masses(1)), save_map(tmp_path / "m2.npz", *masses(2))


# ------------------------------------------------------------------ outputs


def test_export_into_the_model_folder_is_refused_and_the_model_still_loads(fusion_dir, capsys):
    """``export fusion --model D -o D/model.ckpt --force`` replaced the checkpoint."""
    before = _listing(fusion_dir)
    out = fusion_dir / "model.ckpt"
    assert (
        cli.main(["export", "fusion", "--model", str(fusion_dir), "-o", str(out), "--force"]) == 1
    )
    _error_line(capsys, "model folder", str(out))
    assert (
        cli.main(["export", "fusion", "--model", str(fusion_dir), "-o", str(fusion_dir / "x.pt")])
        == 1
    )
    _error_line(capsys, "model folder")
    assert _listing(fusion_dir) == before
    load_fusion_model(fusion_dir)


def test_risk_result_never_replaces_the_model_metadata(tmp_path, risk_dir, capsys):
    """``risk ... -o <model>/model_meta.json --force`` turned the meta into a result."""
    lp, rp = write_stereo_pair(tmp_path / "pair", "f", *textured_pair())
    before = _listing(risk_dir)
    meta = risk_dir / "model_meta.json"
    argv = ["risk", str(lp), str(rp), "--speed", "8.7", "--model", str(risk_dir)]
    assert cli.main([*argv, "-o", str(meta), "--force"]) == 1
    _error_line(capsys, "model folder", "model_meta.json")
    assert cli.main(["export", "risk", "--model", str(risk_dir), "-o", str(meta), "--force"]) == 1
    _error_line(capsys, "model folder")
    assert _listing(risk_dir) == before
    assert load_risk_model(risk_dir).meta["domain"] == DOMAIN


def test_runs_compare_never_overwrites_the_store_or_the_lock(tmp_path, capsys):
    """``runs compare --csv mlflow.db --force`` overwrote the registry database."""
    db = tmp_path / "mlflow.db"
    with sqlite3.connect(db) as con:
        con.execute("create table registered_models (name text)")
    lock = tmp_path / "dvc.lock"
    lock.write_text("schema: '2.0'\nstages: {}\n")
    params = tmp_path / "params.yaml"
    params.write_text("profile: default\n")
    before = _listing(tmp_path)
    uri = f"sqlite:///{tmp_path / 'other.db'}"
    for target, why in ((db, "SQLite database"), (lock, "DVC pipeline"), (params, "DVC pipeline")):
        argv = ["runs", "compare", "--experiment", "risk", "--tracking-uri", uri]
        assert cli.main([*argv, "--csv", str(target), "--force"]) == 1
        _error_line(capsys, "--csv", str(target), why)
    assert _listing(tmp_path) == before


@pytest.mark.parametrize(
    ("parts", "why"),
    [
        (("mlruns", "0", "x.csv"), "mlruns/"),
        (("mlartifacts", "x.csv"), "mlartifacts/"),
        ((".git", "config"), ".git/"),
        (("stage.dvc",), "DVC pipeline"),
    ],
)
def test_stores_and_pipeline_files_are_protected(tmp_path, parts, why):
    assert why in protected_reason(tmp_path.joinpath(*parts))
    assert protected_reason(tmp_path / "results" / "x.csv") is None


def test_force_replaces_only_a_previous_output_of_the_same_kind(tmp_path, fusion_dir, maps):
    """``--force`` over a file of another kind (a text file named ``.npz``, a zip named ``.json``)
    is refused and the file kept; over a previous output of the command it works."""
    text = tmp_path / "notes.npz"
    text.write_text("my notes\n")
    with pytest.raises(OutputError, match=r"notes\.npz exists and is not a previous \.npz output"):
        OutputSet([text], force=True)
    zipped = tmp_path / "r.json"
    zipped.write_bytes(maps[0].read_bytes())
    with pytest.raises(OutputError, match="its content is zip"):
        OutputSet([zipped], force=True)
    assert text.read_text() == "my notes\n"
    out = tmp_path / "f"
    assert cli.main(fuse_args(*maps, fusion_dir, out)) == 0
    first = (tmp_path / "f.npz").read_bytes()
    assert cli.main(fuse_args(*maps, fusion_dir, out, "--force")) == 0
    assert (tmp_path / "f.npz").read_bytes() == first


# ------------------------------------------------------------------ the seal


def _flip_a_bit(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01
    path.write_bytes(bytes(data))


def _edit_meta(folder: Path, **changes) -> None:
    p = folder / "model_meta.json"
    meta = json.loads(p.read_text())
    for k, v in changes.items():
        if v is None:
            meta.pop(k, None)
        else:
            meta[k] = v
    p.write_text(json.dumps(meta))


def test_tampered_checkpoint_with_its_hash_deleted_is_refused(fusion_dir, maps, tmp_path, capsys):
    """Flip a bit of model.ckpt and delete ckpt_sha256: fuse exited 0."""
    _flip_a_bit(fusion_dir / "model.ckpt")
    _edit_meta(fusion_dir, ckpt_sha256=None)
    with pytest.raises(FusionModelError, match="no 'ckpt_sha256'"):
        load_fusion_model(fusion_dir)
    assert cli.main(fuse_args(*maps, fusion_dir, tmp_path / "out")) == 1
    _error_line(capsys, "ckpt_sha256", "model_meta.json")
    assert not list(tmp_path.glob("out*"))


def test_a_model_without_its_metadata_is_refused(fusion_dir, risk_dir):
    (fusion_dir / "model_meta.json").unlink()
    with pytest.raises(FusionModelError, match="model_meta.json: missing"):
        load_fusion_model(fusion_dir)
    (risk_dir / "model_meta.json").unlink()
    with pytest.raises(RiskModelError, match="model_meta.json: missing"):
        load_risk_model(risk_dir)


def test_edited_domain_in_the_metadata_is_refused(risk_dir, tmp_path, capsys):
    """Setting domain.max_speed to 1e9 in the JSON let --speed 5000 through."""
    _edit_meta(risk_dir, domain={**DOMAIN, "max_speed": 1e9, "speed_range": [0.0, 1e9]})
    with pytest.raises(RiskModelError, match="'domain' differs from the checkpoint"):
        load_risk_model(risk_dir)
    lp, rp = write_stereo_pair(tmp_path / "pair", "f", *textured_pair())
    argv = ["risk", str(lp), str(rp), "--speed", "5000", "--model", str(risk_dir)]
    assert cli.main(argv) == 1
    _error_line(capsys, "'domain' differs")


def test_deleted_domain_in_the_metadata_is_refused(risk_dir):
    _edit_meta(risk_dir, domain=None)
    with pytest.raises(RiskModelError, match="'domain' is missing"):
        load_risk_model(risk_dir)


def test_edited_grid_of_a_fusion_model_is_refused(fusion_dir):
    _edit_meta(fusion_dir, grid={"rows": 64, "cols": 64, "cell": 0.5})
    with pytest.raises(FusionModelError, match="'grid' differs from the checkpoint"):
        load_fusion_model(fusion_dir)


@pytest.mark.parametrize(
    ("content", "needle"),
    [
        (b"[]", "expected a JSON object of model metadata, got list"),
        (b"null", "got NoneType"),
        (b'"a string"', "got str"),
        (b"\xff\xfe\x00garbage", "not UTF-8 text"),
        (b"{", "not valid JSON"),
    ],
)
def test_malformed_metadata_is_one_line(risk_dir, fusion_dir, tmp_path, content, needle, capsys):
    """``model_meta.json`` that is ``[]``, ``null``, a string or non-UTF-8 gave an
    ``AttributeError`` / ``UnicodeDecodeError`` traceback."""
    for folder in (risk_dir, fusion_dir):
        (folder / "model_meta.json").write_bytes(content)
    with pytest.raises(RiskModelError, match=needle):
        load_risk_model(risk_dir)
    with pytest.raises(api.ApiError, match=needle):
        api.load_fusion(fusion_dir)
    maps = save_map(tmp_path / "a.npz", *masses(1)), save_map(tmp_path / "b.npz", *masses(2))
    assert cli.main(fuse_args(*maps, fusion_dir, tmp_path / "o")) == 1
    _error_line(capsys, "model_meta.json", needle)


def test_logged_artifacts_carry_the_seal(cl):
    """MLflow artifacts go through the same loaders: :func:`traffictwin.trainer.log_model` writes
    the checkpoint's hash into the artifact's model_meta.json, so the seal check holds there."""
    from _registry_models import log_linear
    from _tamper import artifact_dir

    from traffictwin.io.shards import sha256_file
    from traffictwin.mlops import model_artifact as art
    from traffictwin.mlops import registry as reg
    from traffictwin.model_format import CKPT_SHA_KEY, check_model_pair, read_model_meta

    mv = reg.ensure_version(cl, "traffictwin-seal", log_linear(0.5))
    folder = artifact_dir(cl, "traffictwin-seal", mv.version)
    meta = read_model_meta(folder / art.META)
    assert meta[CKPT_SHA_KEY] == sha256_file(folder / art.CKPT)
    check_model_pair(folder / art.CKPT, meta)


def test_failing_registry_load_is_one_line_without_a_progress_bar(
    tmp_path, mlflow_uri, monkeypatch, capsys
):
    """A failing registry load printed ``Downloading artifacts: 0/112`` before its
    one-line error."""
    import mlflow
    import torch
    from _tamper import artifact_dir

    from traffictwin.mlops import registry as reg
    from traffictwin.trainer import log_model

    monkeypatch.chdir(tmp_path)
    for k in ("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR",):
        monkeypatch.delenv(k, raising=False)  # as on a fresh shell: the CLI sets it
    cl = reg.client(mlflow_uri)
    folder = save_fusion_model(tmp_path / "m")
    net = load_fusion_model(folder)
    ckpt = torch.load(folder / "model.ckpt", weights_only=True)
    mlflow.set_experiment("fusion")
    with mlflow.start_run() as run:
        log_model(ckpt, ckpt["traffictwin"], net, torch.zeros(1, 4, 32, 48).numpy())
    mv = reg.ensure_version(cl, "traffictwin-fusion", run.info.run_id)
    cl.set_registered_model_alias("traffictwin-fusion", "champion", mv.version)
    (artifact_dir(cl, "traffictwin-fusion", mv.version) / "model_meta.json").write_text("{}")
    maps = save_map(tmp_path / "a.npz", *masses(1)), save_map(tmp_path / "b.npz", *masses(2))
    argv = [*fuse_args(*maps, "champion", tmp_path / "o"), "--tracking-uri", mlflow_uri]
    capsys.readouterr()  # what the setup printed
    assert cli.main(argv) == 1
    line = _error_line(capsys, "traffictwin-fusion")
    assert "Downloading" not in line
