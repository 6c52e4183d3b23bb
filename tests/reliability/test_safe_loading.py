"""Loading a registered model must never run code from its artifact.

Models are logged as weights + JSON (traffictwin flavour) with the SHA-256 of every file recorded
at logging and on the registered version; a replaced file is refused before anything reads it,
and a model logged as an ``mlflow.pytorch`` pickle (older versions) is refused without unpickling.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from _registry_models import load_linear, log_linear
from _tamper import artifact_dir, payload_runs, write_malicious_pickle

from traffictwin.mlops import model_artifact as art
from traffictwin.mlops import registry as reg

NAME = "traffictwin-fusion-T"


def _registered(cl, weight: float = 1.0):
    return reg.ensure_version(cl, NAME, log_linear(weight))


def test_logged_model_is_weights_and_json_with_a_hash_record(cl):
    mv = _registered(cl, 0.5)
    folder = artifact_dir(cl, NAME, mv.version)
    names = {p.name for p in folder.iterdir()}
    # + the pyfunc packaging (requirements; no code)
    assert {art.MLMODEL, art.CKPT, art.META} <= names
    assert not {n for n in names if n.endswith((".pkl", ".pickle", ".pth"))}, names
    record = json.loads(mv.tags[art.SHA_TAG])
    assert record == art.file_hashes(folder)  # every file, as recorded at logging
    block = art.read_flavor(folder, "x")
    assert block["format"] == art.ARTIFACT_FORMAT and block["problem"] == "linear"
    assert "pytorch" not in (folder / art.MLMODEL).read_text()  # no pickled flavour
    torch.load(folder / art.CKPT, weights_only=True)  # plain tensors and containers
    model = reg.load_registered(reg.version_uri(NAME, mv.version), load_linear, cl=cl)
    assert model.weight.detach().numpy().tolist() == [[0.5, 0.5]]
    # the signature is kept on the MLflow model
    import mlflow.models

    sig = mlflow.models.get_model_info(reg.version_uri(NAME, mv.version)).signature
    assert sig is not None and sig.inputs.inputs[0].shape == (-1, 2)


def test_tampered_checkpoint_is_refused_before_unpickling(cl, tmp_path):
    mv = _registered(cl)
    cl.set_registered_model_alias(NAME, "champion", mv.version)
    ckpt = artifact_dir(cl, NAME, mv.version) / art.CKPT
    marker = tmp_path / "pwned"
    write_malicious_pickle(ckpt, marker)
    with pytest.raises(reg.TamperedArtifactError) as exc:
        reg.load_registered(f"models:/{NAME}@champion", load_linear, cl=cl)
    assert not marker.exists(), "the replaced artifact was unpickled"
    msg = str(exc.value)
    assert f"model '{NAME}' v{mv.version}" in msg and "model.ckpt" in msg and "\n" not in msg
    # the payload is real: unpickling it unsafely would have run it
    probe = tmp_path / "probe.ckpt"
    probe.write_bytes(ckpt.read_bytes())
    assert payload_runs(probe, marker)


def test_hash_mismatch_message_names_model_version_file_and_hashes(cl):
    mv = _registered(cl)
    meta = artifact_dir(cl, NAME, mv.version) / art.META
    recorded = json.loads(mv.tags[art.SHA_TAG])[art.META]
    meta.write_text(meta.read_text().replace("1", "2", 1))
    found = art.file_hashes(meta.parent, [art.META])[art.META]
    with pytest.raises(reg.TamperedArtifactError) as exc:
        reg.load_registered(reg.version_uri(NAME, mv.version), load_linear, cl=cl)
    assert str(exc.value) == (
        f"model '{NAME}' v{mv.version}: artifact file {art.META} does not match the SHA-256 "
        f"recorded at registration (recorded {recorded[:12]}…, found {found[:12]}…): it was "
        "replaced or corrupted; refusing to load it"
    )


def test_missing_artifact_file_is_refused(cl):
    mv = _registered(cl)
    (artifact_dir(cl, NAME, mv.version) / art.CKPT).unlink()
    with pytest.raises(reg.TamperedArtifactError, match=r"artifact file model.ckpt is missing"):
        reg.load_registered(reg.version_uri(NAME, mv.version), load_linear, cl=cl)


def test_file_replaced_between_logging_and_registration_is_not_registered(cl, tmp_path):
    run_id = log_linear(1.0)
    (lm,) = cl.search_logged_models(experiment_ids=[cl.get_run(run_id).info.experiment_id])
    folder = artifact_dir_of_logged(cl, lm.model_id)
    write_malicious_pickle(folder / art.CKPT, tmp_path / "pwned")
    with pytest.raises(reg.TamperedArtifactError, match=rf"run '{run_id}'.*model.ckpt"):
        reg.ensure_version(cl, NAME, run_id)
    assert cl.search_model_versions(f"name='{NAME}'") == []
    assert not (tmp_path / "pwned").exists()


def artifact_dir_of_logged(cl, model_id: str):
    from pathlib import Path
    from urllib.parse import unquote, urlparse

    loc = cl.get_logged_model(model_id).artifact_location
    u = urlparse(loc)
    return Path(unquote(u.path) if u.scheme == "file" else loc)


def test_version_without_hash_record_is_refused_then_sealed_by_ensure_version(cl):
    """A version registered behind the gate's back (plain mlflow.register_model) has no record:
    it is not loaded; ensure_version checks it against the logging-time record and seals it."""
    import mlflow

    run_id = log_linear(2.0)
    (lm,) = cl.search_logged_models(experiment_ids=[cl.get_run(run_id).info.experiment_id])
    mv = mlflow.register_model(f"models:/{lm.model_id}", NAME)
    uri = reg.version_uri(NAME, mv.version)
    with pytest.raises(reg.ModelArtifactError, match="no SHA-256 recorded"):
        reg.load_registered(uri, load_linear, cl=cl)
    sealed = reg.ensure_version(cl, NAME, run_id)
    assert sealed.version == mv.version and art.SHA_TAG in sealed.tags
    assert reg.load_registered(uri, load_linear, cl=cl).weight.sum().item() == 4.0


def test_logged_model_uri_loads_with_the_logging_record(cl):
    run_id = log_linear(3.0)
    (lm,) = cl.search_logged_models(experiment_ids=[cl.get_run(run_id).info.experiment_id])
    uri = f"models:/{lm.model_id}"
    assert reg.load_registered(uri, load_linear, cl=cl).weight.sum().item() == 6.0
    (artifact_dir_of_logged(cl, lm.model_id) / art.META).write_text("{}")
    with pytest.raises(reg.TamperedArtifactError, match=f"logged model {lm.model_id}"):
        reg.load_registered(uri, load_linear, cl=cl)


def _legacy_version(cl, tmp_path, marker):
    """A version registered the old way (mlflow.pytorch pickle) whose pickle now runs code."""
    import mlflow

    mlflow.set_experiment("legacy")
    with mlflow.start_run() as run:
        mlflow.pytorch.log_model(
            torch.nn.Linear(2, 1), name="model", serialization_format="pickle", pip_requirements=[]
        )
    mv = mlflow.register_model(f"runs:/{run.info.run_id}/model", NAME)
    folder = artifact_dir(cl, NAME, mv.version)
    (pickled,) = [p for p in folder.rglob("*.pth")]
    write_malicious_pickle(pickled, marker)
    return run.info.run_id, mv


def test_legacy_pickled_version_is_refused_without_unpickling(cl, tmp_path):
    marker = tmp_path / "pwned"
    run_id, mv = _legacy_version(cl, tmp_path, marker)
    with pytest.raises(reg.LegacyModelError) as exc:
        reg.load_registered(reg.version_uri(NAME, mv.version), load_linear, cl=cl)
    msg = str(exc.value)
    assert f"model '{NAME}' v{mv.version}" in msg and "pickled mlflow.pytorch" in msg
    assert "re-register" in msg and "\n" not in msg
    assert isinstance(exc.value, reg.IncompatibleModelError)  # the gate may skip such a champion
    # registering the old run is refused too (it would seal a pickle)
    with pytest.raises(reg.LegacyModelError):
        reg.ensure_version(cl, NAME, run_id)
    assert not marker.exists(), "the legacy pickle was unpickled"
    (pickled,) = list(artifact_dir(cl, NAME, mv.version).rglob("*.pth"))
    assert payload_runs(pickled, marker)  # ... though unpickling it would have run the payload


def test_cli_risk_refuses_a_tampered_registered_model(cl, tmp_path, capsys, monkeypatch):
    """`traffictwin risk --model champion` loads through the checked loader."""
    monkeypatch.setenv("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")
    import cv2
    import mlflow

    from traffictwin import cli
    from traffictwin.risk.dave2 import Dave2, Dave2Config, PackedDave2
    from traffictwin.risk.model_io import risk_checkpoint, risk_meta, save_risk_model
    from traffictwin.trainer import log_model

    torch.manual_seed(0)
    net = Dave2(Dave2Config()).eval()
    meta = {"label": "risk"}
    mlflow.set_experiment("risk")
    with mlflow.start_run() as run:
        log_model(
            risk_checkpoint(net, meta),
            risk_meta(net, meta),
            PackedDave2(net),
            np.zeros((1, net.cfg.in_channels, net.cfg.height, net.cfg.width), np.float32),
        )
    mv = reg.ensure_version(cl, reg.RISK_NAME, run.info.run_id)
    cl.set_registered_model_alias(reg.RISK_NAME, "champion", mv.version)
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.integers(0, 256, (120, 200, 3), dtype=np.uint8), (3, 3), 0)
    cv2.imwrite(str(tmp_path / "l.png"), img[:, :190])
    cv2.imwrite(str(tmp_path / "r.png"), img[:, 4:194])
    args = ["risk", str(tmp_path / "l.png"), str(tmp_path / "r.png"), "--model", "champion"]
    assert cli.main([*args, "-o", str(tmp_path / "ok.json")]) == 0
    folder = save_risk_model(net, tmp_path / "local", meta)
    assert cli.main([*args[:3], "--model", str(folder), "-o", str(tmp_path / "path.json")]) == 0
    ok = json.loads((tmp_path / "ok.json").read_text())
    assert ok["risk"] == json.loads((tmp_path / "path.json").read_text())["risk"]
    marker = tmp_path / "pwned"
    write_malicious_pickle(artifact_dir(cl, reg.RISK_NAME, mv.version) / art.CKPT, marker)
    # the CLI's verified copy holds exactly the recorded files: served, nothing unpickled
    assert cli.main([*args, "-o", str(tmp_path / "cached.json")]) == 0 and not marker.exists()
    import shutil

    shutil.rmtree(reg.model_cache_root())  # cold: the store's tampered file is refused
    capsys.readouterr()
    assert cli.main([*args, "-o", str(tmp_path / "bad.json")]) == 1
    err = capsys.readouterr().err.strip()
    assert "traffictwin-risk' v1: artifact file model.ckpt does not match" in err
    assert len(err.splitlines()) == 1 and not marker.exists(), err
    assert not (tmp_path / "bad.json").exists()


def test_a_registry_load_reuses_its_verified_copy_and_drops_an_altered_one(cl):
    """Interactive registry loads cost about a folder load: the second load reads the
    verified copy kept by the first (no download); a copy altered since is dropped and downloaded
    again; the promotion gate's loads never use the cache."""
    from unittest import mock

    mv = _registered(cl, 0.25)
    uri = reg.version_uri(NAME, mv.version)
    assert reg.load_registered(uri, load_linear, cl=cl, cache=True).weight.sum().item() == 0.5
    (kept,) = [p for p in reg.model_cache_root().iterdir() if not p.name.startswith(".")]
    from traffictwin.mlops import registry_loading  # where load_registered looks them up

    with mock.patch.object(
        registry_loading, "_download", side_effect=AssertionError("downloaded again")
    ):
        assert reg.load_registered(uri, load_linear, cl=cl, cache=True).weight.sum().item() == 0.5
    write_malicious_pickle(kept / art.CKPT, kept / "pwned")  # the cache altered on disk
    assert reg.load_registered(uri, load_linear, cl=cl, cache=True).weight.sum().item() == 0.5
    # the gate (no cache) always reads the store
    with mock.patch.object(
        registry_loading, "_cached_copy", side_effect=AssertionError("cache used")
    ):
        assert reg.load_registered(uri, load_linear, cl=cl).weight.sum().item() == 0.5
    assert not (kept / "pwned").exists()
