"""Registry references and messages: a local folder never shadows a registry reference, and a
password (or token) in a tracking URI never reaches a message."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from traffictwin import cli
from traffictwin.mlops import registry as reg
from traffictwin.mlops.uris import mask_secrets, mask_uri


@pytest.mark.parametrize(
    "text, name, alias",
    [
        ("traffictwin-risk@champion", "traffictwin-risk", "champion"),
        ("models:/traffictwin-risk@challenger", "traffictwin-risk", "challenger"),
        ("champion", None, "champion"),
    ],
)
def test_a_reference_resolves_against_the_registry_even_beside_a_folder_of_its_name(
    tmp_path, monkeypatch, text, name, alias
):
    monkeypatch.chdir(tmp_path)
    folder = tmp_path / text.removeprefix("models:/")
    folder.mkdir(parents=True)
    (folder / "model_meta.json").write_text("{}")
    assert reg.split_model_reference(text) == (name, alias, None)
    # the folder is reached as a path, with a directory part
    assert reg.split_model_reference(f"./{text.removeprefix('models:/')}") == (
        None,
        None,
        folder.relative_to(tmp_path),
    )
    assert folder.is_dir()  # untouched


def test_cli_never_loads_a_folder_named_like_the_reference(tmp_path, monkeypatch, capsys):
    """``risk --model traffictwin-risk@champion`` beside a folder of that name holding another
    model: the registry is asked (here: none, one line, exit 1) and the folder is not loaded;
    ``./traffictwin-risk@champion`` is the folder, reported as that path."""
    import json

    from _cli_models import save_risk, textured_pair, write_pair

    monkeypatch.chdir(tmp_path)
    folder = save_risk(tmp_path / "traffictwin-risk@champion")
    lp, rp = write_pair(tmp_path / "in", "f", *textured_pair())
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    db = tmp_path / "none.db"
    argv = ["risk", str(lp), str(rp), "--model", "traffictwin-risk@champion"]
    assert cli.main([*argv, "--tracking-uri", f"sqlite:///{db}"]) == 1
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert out == "" and len(lines) == 1 and "no MLflow database" in lines[0], lines
    assert not db.exists()
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before
    assert cli.main(["risk", str(lp), str(rp), "--model", "./traffictwin-risk@champion"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["model"] == "./traffictwin-risk@champion", res["model"]  # a path, read as one


def test_a_path_is_a_path_and_a_bad_reference_is_one_line(tmp_path):
    d = tmp_path / "m"
    d.mkdir()
    assert reg.split_model_reference(d) == (None, None, d)
    for text, needle in [
        (str(tmp_path / "missing"), "neither a registry reference"),
        ("@champion", "not a registry reference"),
        ("traffictwin-risk@", "not a registry reference"),
    ]:
        with pytest.raises(reg.RegistryError) as info:
            reg.split_model_reference(text)
        assert needle in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize(
    "uri, secret",
    [
        ("postgresql://u:secret@127.0.0.1:9/x", "secret"),
        ("mysql+pymysql://user:p%40ss@db.example/mlflow", "p%40ss"),
        ("https://mlflow.example/api?token=tok123&x=1", "tok123"),
        ("http://a:b@c@127.0.0.1:9", "b@c"),
    ],
)
def test_secrets_in_uris_are_masked(uri, secret):
    masked = mask_uri(uri)
    assert secret not in masked and "***" in masked
    assert (
        mask_secrets(f"{uri}: model registry unreachable")
        == f"{masked}: model registry unreachable"
    )
    assert mask_uri("sqlite:////tmp/a@b/mlflow.db") == "sqlite:////tmp/a@b/mlflow.db"


@pytest.mark.parametrize("command", [["status"], ["rollback", "--model", "traffictwin-fusion"]])
def test_registry_commands_never_print_the_password(capsys, command):
    uri = "postgresql://u:secret@127.0.0.1:9/x"
    assert cli.main([*command, "--tracking-uri", uri]) == 1
    out, err = capsys.readouterr()
    assert "secret" not in out + err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "postgresql://u:***@127.0.0.1:9/x" in lines[0], lines


def test_a_model_file_is_refused_with_its_folder_named(tmp_path):
    meta = tmp_path / "m" / "model_meta.json"
    meta.parent.mkdir()
    meta.write_text("{}")
    with pytest.raises(reg.RegistryError) as info:
        reg.split_model_reference(meta)
    msg = str(info.value)
    assert f"pass the model folder that holds it ({meta.parent})" in msg
    assert "weights_only" not in msg


# ------------------------------------------------------------------ one line instead of a traceback


def test_promote_on_a_file_that_is_not_a_database_is_one_line(tmp_path, monkeypatch, capsys):
    from pipelines import promote as pm

    db = tmp_path / "r.db"
    db.write_bytes(np.random.default_rng(0).bytes(4096))
    before = db.read_bytes()
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{db}")
    monkeypatch.setattr(pm, "build_jobs", lambda cfg, rc: [])
    assert pm.main(["--dry-run"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"promote: error: {db}: not an MLflow database (not a SQLite file) — check "
        "MLFLOW_TRACKING_URI / --tracking-uri"
    ]
    assert db.read_bytes() == before


def test_read_only_sqlite_uri_opens_the_registry_read_only(cl, mlflow_uri):
    from mlflow.exceptions import MlflowException

    from traffictwin.mlops.stores import sqlite_path

    cl.create_registered_model("traffictwin-ro")
    db = Path(mlflow_uri.removeprefix("sqlite:///"))
    before = db.read_bytes()
    ro = f"{mlflow_uri}?mode=ro"
    assert sqlite_path(ro) == db
    ro_client = reg.client(ro)
    assert reg.registered_names(ro_client) == ["traffictwin-ro"]
    with pytest.raises(MlflowException, match="readonly"):  # really read-only
        ro_client.create_registered_model("traffictwin-w")
    assert cli.main(["status", "--tracking-uri", ro]) == 0  # the CLI takes it too
    assert db.read_bytes() == before


def test_status_of_an_unknown_model_exits_1_with_one_line(cl, mlflow_uri, capsys):
    cl.create_registered_model("traffictwin-fusion")
    assert cli.main(["status", "--model", "nope", "--tracking-uri", mlflow_uri]) == 1
    out, err = capsys.readouterr()
    assert out == ""
    assert err.strip().splitlines() == [
        "traffictwin status: error: --model: no registered model 'nope' "
        "(registered: traffictwin-fusion)"
    ]


def test_gate_says_which_figure_is_missing_instead_of_nan():
    from traffictwin.mlops.gate import Gate, compare

    better, why = compare(Gate("test/mse", "min", 0.01), float("nan"), 0.5)
    assert not better and "nan >" not in why and "improvement nan" not in why
    assert "no finite figure for the challenger" in why
