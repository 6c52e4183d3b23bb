"""Served code is the installed code: a registered model's artifact carries no executable project
code, so code appended to anything in it never runs on ``mlflow.pyfunc.load_model`` or a predict.

A tiny DAVE-2 (speed input, 8 x 8 px) is logged and registered as ``champion`` in a temp SQLite
store; the tampering and the load happen in a separate interpreter (bounded by a timeout), so a
payload that did run could not touch this test process.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from _tamper import artifact_dir

from traffictwin.mlops import model_artifact as art
from traffictwin.mlops import registry as reg
from traffictwin.mlops import serving
from traffictwin.mlops.errors import IncompatibleModelError
from traffictwin.risk.dave2 import Dave2, Dave2Config, PackedDave2
from traffictwin.risk.model_io import risk_checkpoint, risk_meta, save_risk_model
from traffictwin.trainer import log_model

NAME = "traffictwin-risk-T"
TINY = {"height": 8, "width": 8, "conv": ((4, 3, 1),), "fc": (4,), "use_speed": True}


def _example() -> np.ndarray:
    g = np.random.default_rng(0)
    x = np.empty((2, 5, 8, 8), np.float32)
    x[:, :3] = g.uniform(-1, 1, (2, 3, 8, 8))
    x[:, 3] = g.uniform(0, 1, (2, 8, 8))
    x[:, 4] = 10.0  # m/s
    return x


def _champion(cl) -> Path:
    """Register a tiny risk model as champion; the folder of its artifact in the store."""
    import mlflow

    torch.manual_seed(0)
    net = Dave2(Dave2Config(**TINY)).eval()
    meta = {"variant": "t", "domain": {"speed_range": [0.0, 25.0]}}
    mlflow.set_experiment("risk")
    with mlflow.start_run() as run:
        log_model(risk_checkpoint(net, meta), risk_meta(net, meta), PackedDave2(net), _example())
    mv = reg.ensure_version(cl, NAME, run.info.run_id)
    cl.set_registered_model_alias(NAME, "champion", mv.version)
    return artifact_dir(cl, NAME, mv.version)


def _load_and_predict(tmp_path: Path, marker: Path) -> subprocess.CompletedProcess:
    x_path = tmp_path / "x.npy"
    np.save(x_path, _example())
    script = textwrap.dedent(
        f"""
        import numpy as np, mlflow
        m = mlflow.pyfunc.load_model("models:/{NAME}@champion")
        print("loaded; marker:", __import__("os").path.exists({str(marker)!r}))
        y = m.predict(np.load({str(x_path)!r}))
        print("predicted", y.shape)
        """
    )
    return subprocess.run(
        [sys.executable, "-c", script],
        cwd=tmp_path,
        env=dict(os.environ),
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_appended_code_in_the_artifact_never_runs_on_pyfunc_load_or_predict(cl, tmp_path):
    folder = _champion(cl)
    files = [p for p in folder.rglob("*") if p.is_file()]
    assert not (folder / "code").exists(), sorted(p.name for p in folder.iterdir())
    assert not [p for p in files if p.suffix in (".py", ".pyc", ".so", ".pth")], files
    pyfunc = yaml.safe_load((folder / art.MLMODEL).read_text())["flavors"]["python_function"]
    assert "code" not in pyfunc and pyfunc["loader_module"] == serving.__name__

    marker = tmp_path / "PWNED"
    payload = f"\nopen({str(marker)!r}, 'w').write('ran')\n"
    # append to every file of the artifact that is (or once was) importable code, and plant the
    # package where earlier versions shipped it (code/traffictwin/...), as a writer of the store could
    planted = [
        folder / "code" / "traffictwin" / "__init__.py",
        folder / "code" / "traffictwin" / "mlops" / "__init__.py",
        folder / "code" / "traffictwin" / "mlops" / "serving.py",
    ]
    for p in planted:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(payload)
    for p in files:
        if p.suffix in (".py", ".txt", ".yaml"):
            with p.open("a") as fh:
                fh.write(payload)
    proc = _load_and_predict(tmp_path, marker)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "loaded; marker: False" in proc.stdout and "predicted (2,)" in proc.stdout, proc.stdout
    assert not marker.exists()
    # the champion did not move
    assert str(reg.get_alias(cl, NAME, "champion").version) == "1"


def test_a_model_of_another_traffictwin_release_is_refused_before_it_is_built(tmp_path):
    from mlflow.models import Model

    net = Dave2(Dave2Config(**TINY)).eval()
    src = save_risk_model(net, tmp_path / "src", {"label": "risk"})
    folder = tmp_path / "m"
    art.save_model(
        str(folder),
        Model(),
        files={art.CKPT: src / art.CKPT, art.META: src / art.META},
        problem="risk",
    )
    block = art.read_flavor(folder, "m")
    assert block[art.VERSION_KEY] == art.installed_version()
    serving._load_pyfunc(str(folder))  # the installed release: loads
    doc = yaml.safe_load((folder / art.MLMODEL).read_text())
    doc["flavors"][art.FLAVOR][art.VERSION_KEY] = "99.0.0"
    (folder / art.MLMODEL).write_text(yaml.safe_dump(doc))
    with pytest.raises(IncompatibleModelError) as info:
        serving._load_pyfunc(str(folder))
    msg = str(info.value)
    assert "logged by traffictwin 99.0.0" in msg and art.installed_version() in msg, msg
    assert "\n" not in msg
