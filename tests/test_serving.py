"""Logged models as MLflow pyfunc models served by the installed traffictwin.

A small risk network (DAVE-2 with the speed input, random seeded weights) is logged with
:func:`traffictwin.trainer.log_model` to a temp SQLite store, then loaded with
``mlflow.pyfunc.load_model`` in a fresh interpreter: the model carries no code, so the pyfunc
imports the installed package; an interpreter without it (``python -S``: no ``.pth`` file, no
editable install) cannot load the model and says that ``traffictwin`` is missing.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import sysconfig
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from traffictwin.mlops import model_artifact as art
from traffictwin.mlops import serving
from traffictwin.risk.dave2 import Dave2, Dave2Config, PackedDave2
from traffictwin.risk.model_io import risk_checkpoint, risk_meta
from traffictwin.trainer import log_model


def _logged_risk_model(tmp_path: Path) -> tuple[str, np.ndarray, np.ndarray]:
    """Log a seeded DAVE-2 (speed input) in a new run; ``(model_uri, example, eager output)``."""
    import mlflow

    torch.manual_seed(3)
    net = Dave2(Dave2Config(use_speed=True)).eval()
    packed = PackedDave2(net).eval()
    g = np.random.default_rng(5)
    example = g.normal(size=(2, net.cfg.in_channels + 1, 66, 200)).astype(np.float32)
    example[:, -1] = np.array([8.0, 21.5], np.float32)[:, None, None]  # speed planes, m/s
    with torch.no_grad():
        eager = packed(torch.from_numpy(example)).numpy()
    mlflow.set_experiment("risk")
    with mlflow.start_run():
        uri = log_model(
            risk_checkpoint(net, {"variant": "t"}),
            risk_meta(net, {"variant": "t"}),
            packed,
            example,
        )
    return uri, example, eager


def test_model_directory_has_pyfunc_code_requirements_and_example(
    cl, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import mlflow
    import mlflow.models.utils

    validated: list[str] = []  # MLflow's own serving check is off (model_artifact.log_model)
    monkeypatch.setattr(
        mlflow.models.utils, "_validate_serving_input", lambda uri, _: validated.append(uri)
    )
    uri, example, _ = _logged_risk_model(tmp_path)
    assert validated == []
    folder = Path(mlflow.artifacts.download_artifacts(uri, dst_path=str(tmp_path / "dl")))
    mlmodel = yaml.safe_load((folder / "MLmodel").read_text())
    pyfunc = mlmodel["flavors"]["python_function"]
    assert pyfunc["loader_module"] == "traffictwin.mlops.serving"
    assert "code" not in pyfunc  # no executable code: the installed package serves it
    assert mlmodel["flavors"]["traffictwin"][art.VERSION_KEY] == art.installed_version()
    assert mlmodel["flavors"]["traffictwin"]["problem"] == "risk"
    assert "pickled_model" not in json.dumps(mlmodel) and "python_model" not in pyfunc
    assert not (folder / "code").exists()
    assert not [p for p in folder.rglob("*") if p.suffix in (".py", ".pyc", ".pth", ".so")]
    # requirements: pinned, torch with the CPU index, never traffictwin itself
    reqs = (folder / "requirements.txt").read_text().splitlines()
    assert reqs[0] == f"--extra-index-url {art.TORCH_CPU_INDEX}"
    pinned = dict(r.split("==") for r in reqs[1:])
    assert pinned["torch"] == torch.__version__ and pinned["numpy"] == np.__version__
    assert not any("traffictwin" in r for r in reqs)
    # the input example is the logged array
    ex = json.loads((folder / mlmodel["saved_input_example_info"]["artifact_path"]).read_text())
    np.testing.assert_array_equal(np.asarray(ex, np.float32), example)
    # ... and the serving example (what POST /invocations takes) the same array, which the next
    # test's pyfunc turns into the eager network's output
    serving_ex = json.loads((folder / "serving_input_example.json").read_text())
    np.testing.assert_array_equal(np.asarray(serving_ex["inputs"], np.float32), example)
    # every file the flavour wrote is sealed by the SHA-256 record (MLflow
    # adds two descriptive files after the flavour's save_model hook returns)
    lm = cl.get_logged_model(uri.removeprefix("models:/"))
    record = art.decode_hashes(lm.tags[art.SHA_TAG], "t")
    files = {p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file()}
    assert set(record) <= files
    assert files - set(record) <= {"registered_model_meta", "serving_input_example.json"}
    assert "requirements.txt" in record
    art.verify(folder, record, "t")


def _python_script(uri: str, x_path: Path, y_path: Path, clean: bool) -> str:
    site = sysconfig.get_paths()["purelib"]
    head = (
        f"""
        import sys
        sys.path.append({site!r})  # the venv's packages, but no .pth file (no editable install)
        try:
            import traffictwin
        except ImportError:
            pass
        else:
            raise SystemExit("traffictwin is importable in the clean interpreter: " + traffictwin.__file__)
        """
        if clean
        else ""
    )
    return textwrap.dedent(head) + textwrap.dedent(
        f"""
        import numpy as np
        import mlflow
        mlflow.set_tracking_uri({os.environ["MLFLOW_TRACKING_URI"]!r})
        model = mlflow.pyfunc.load_model({uri!r})
        import traffictwin
        print("traffictwin from", traffictwin.__file__)
        np.save({str(y_path)!r}, model.predict(np.load({str(x_path)!r})))
        """
    )


def test_pyfunc_loads_the_installed_package_and_predicts_like_the_eager_model(
    cl, tmp_path: Path
) -> None:
    uri, example, eager = _logged_risk_model(tmp_path)
    x_path, y_path = tmp_path / "x.npy", tmp_path / "y.npy"
    np.save(x_path, example)
    work = tmp_path / "w"
    work.mkdir()
    proc = subprocess.run(
        [sys.executable, "-c", _python_script(uri, x_path, y_path, clean=False)],
        cwd=work,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:] + proc.stdout[-2000:]
    src = proc.stdout.split("traffictwin from", 1)[1].strip().splitlines()[0]
    assert src == str(Path(serving.__file__).parents[1] / "__init__.py")  # the installed source
    np.testing.assert_array_equal(np.load(y_path), eager)

    # without the package the model cannot load: it brings no code of its own
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTHON")}
    proc = subprocess.run(
        [sys.executable, "-S", "-c", _python_script(uri, x_path, y_path, clean=True)],
        cwd=work,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode != 0
    assert "No module named 'traffictwin'" in proc.stderr, proc.stderr[-2000:]


def test_unknown_problem_is_refused_with_the_folder_named(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=f"{tmp_path}.*'nonsense'"):
        serving._network("nonsense", tmp_path)
