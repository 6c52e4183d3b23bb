"""MLflow models without pickled code: weights + JSON, sealed by SHA-256.

A trained network goes to MLflow as a model directory of the ``traffictwin`` flavour:

- ``model.ckpt`` — the one checkpoint format of :mod:`traffictwin.trainer` (tensors and plain
  containers only, read back with ``torch.load(weights_only=True)``);
- ``model_meta.json`` — the architecture and meta of the model, as JSON;
- ``MLmodel`` — MLflow's description (signature, input example, metadata, the ``traffictwin``
  flavour block: format, problem, file names) and a ``python_function`` flavour
  (``loader_module: traffictwin.mlops.serving``, see :mod:`traffictwin.mlops.serving`);
- no executable code: the pyfunc flavour names ``loader_module: traffictwin.mlops.serving`` and
  no ``code`` folder, so ``mlflow.pyfunc.load_model`` and ``mlflow models serve`` import the
  *installed* ``traffictwin`` (of a compatible version: :data:`VERSION_KEY` of the flavour block,
  checked by :func:`check_installed_version` before the model is built). Nothing a writer of the
  artifact store appends to the artifact is ever imported;
- ``requirements.txt``, ``python_env.yaml``, ``conda.yaml`` — pinned requirements without
  ``traffictwin`` (:func:`pip_requirements`; no package index holds the project, and a name
  looked up on a public index could be anyone's), so serve from an environment where the
  project is installed (``--env-manager local``);
- ``input_example.json`` / ``serving_input_example.json`` — the example the signature came from.

No pickle and no code anywhere: the weights are read with ``weights_only=True``. A model logged by
an earlier version of the project carries the package source under ``code/``, which MLflow's own
loader would put on ``sys.path``: re-log it (retrain, ``python -m pipelines.promote``); the
project's loader (:func:`traffictwin.mlops.registry.load_registered`) never imports it.

:func:`log_model` writes the directory with MLflow's ``Model.log`` (so the logged model, its
signature and the registry work as for any flavour), computes the SHA-256 of every file it wrote
and records them as the tag :data:`SHA_TAG` on the logged model. Registration
(:func:`traffictwin.mlops.registry.ensure_version`) checks the files against that record and
copies it onto the registered version; loading (:func:`traffictwin.mlops.registry.load_registered`)
checks the downloaded files against the version's record with :func:`verify` *before* anything
reads them, so a replaced artifact file is refused before any of it is deserialised.

A model logged by an older version of the project (``mlflow.pytorch``, pickled module) is
recognised from its ``MLmodel`` file alone (YAML, read with ``yaml.safe_load``) and refused with
:class:`LegacyModelError`; it is never unpickled.

This module knows no problem (fusion, risk) and no checkpoint layout: it copies files, hashes
them and reads JSON/YAML. Problem loaders are passed in by the caller.
"""

from __future__ import annotations

import importlib.metadata as md
import json
import shutil
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from traffictwin.io.shards import sha256_file
from traffictwin.mlops.errors import GateError, IncompatibleModelError

# the pyfunc loader module MLflow imports when it loads a logged model (by name: it imports this module)
SERVING_MODULE = "traffictwin.mlops.serving"
# distributions the pyfunc load imports directly (traffictwin.trainer pulls in lightning,
# traffictwin.config omegaconf, the risk network cv2, the registration module scipy/matplotlib)
SERVING_DISTRIBUTIONS = (
    "mlflow",
    "torch",
    "numpy",
    "lightning",
    "torchmetrics",
    "opencv-python-headless",
    "opencv-python",
    "pyyaml",
    "omegaconf",
    "scipy",
    "matplotlib",
)
TORCH_CPU_INDEX = "https://download.pytorch.org/whl/cpu"


def installed_version() -> str:
    """The version of the installed ``traffictwin`` distribution ("unknown" if not installed)."""
    try:
        return md.version("traffictwin")
    except md.PackageNotFoundError:
        return "unknown"


def _release(version: str) -> tuple[str, ...]:
    """The compatibility key of a version: ``major.minor`` (``0.x``: the minor is the major)."""
    return tuple(version.split(".")[:2])


def check_installed_version(block: Mapping[str, Any], who: str) -> None:
    """Refuse a model logged by an incompatible ``traffictwin`` (another ``major.minor`` than the
    installed one): :class:`IncompatibleModelError` naming both versions. A model without the
    record (logged before it was kept) is accepted: its checkpoint format is checked on load."""
    logged = block.get(VERSION_KEY)
    if logged is None:
        return
    have = installed_version()
    if not isinstance(logged, str) or _release(logged) != _release(have):
        raise IncompatibleModelError(
            f"{who}: logged by traffictwin {logged}, the installed traffictwin is {have}; "
            f"install traffictwin {'.'.join(_release(str(logged)))}.x to load it"
        )


def pip_requirements() -> list[str]:
    """``requirements.txt`` lines: the PyTorch CPU index (torch's CPU wheels live only there) and
    every installed distribution of :data:`SERVING_DISTRIBUTIONS`, pinned ``name==version``."""
    lines = [f"--extra-index-url {TORCH_CPU_INDEX}"]
    for dist in SERVING_DISTRIBUTIONS:
        try:
            lines.append(f"{dist}=={md.version(dist)}")
        except md.PackageNotFoundError:
            continue
    return lines


FLAVOR = "traffictwin"
ARTIFACT_FORMAT = "traffictwin-mlflow-model/1"
CKPT = "model.ckpt"
#: the flavour block's record of the traffictwin version that logged the model
VERSION_KEY = "traffictwin_version"
META = "model_meta.json"
MLMODEL = "MLmodel"
SHA_TAG = "traffictwin.sha256"


class ModelArtifactError(GateError):
    """A logged or registered model cannot be used (missing files, no hash record, bad format)."""


class TamperedArtifactError(ModelArtifactError):
    """An artifact file differs from the SHA-256 recorded for it (replaced or corrupted)."""


class LegacyModelError(ModelArtifactError, IncompatibleModelError):
    """A model logged as an ``mlflow.pytorch`` pickle: it is never loaded (that would run its code)."""


#: the request params a served model takes (name, MLflow type; :mod:`traffictwin.mlops.serving`)
SERVING_PARAMS = (("max_batch", "long"),)


def with_serving_params(signature: Any) -> Any:
    """``signature`` with a params schema of :data:`SERVING_PARAMS` (default None: the server's
    limit), so MLflow passes a request's params to ``predict`` instead of dropping them."""
    from mlflow.models import ModelSignature
    from mlflow.types.schema import ParamSchema, ParamSpec

    if getattr(signature, "params", None) is not None:
        return signature
    params = ParamSchema([ParamSpec(n, t, None) for n, t in SERVING_PARAMS])
    return ModelSignature(inputs=signature.inputs, outputs=signature.outputs, params=params)


def file_hashes(
    folder: str | Path, names: list[str] | tuple[str, ...] | None = None
) -> dict[str, str]:
    """SHA-256 (hex) of ``names`` in ``folder`` (default: every file under it, by relative POSIX path)."""
    folder = Path(folder)
    if names is None:
        names = sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file())
    return {n: sha256_file(folder / n) for n in names}


def encode_hashes(hashes: Mapping[str, str]) -> str:
    """The tag value of a hash record (compact JSON, sorted keys)."""
    return json.dumps(dict(sorted(hashes.items())), separators=(",", ":"))


def decode_hashes(value: str | None, who: str) -> dict[str, str]:
    """A hash record from its tag value; :class:`ModelArtifactError` naming ``who`` if unreadable."""
    try:
        rec = json.loads(value or "")
    except json.JSONDecodeError:
        rec = None
    if (
        not isinstance(rec, dict)
        or not rec
        or not all(isinstance(k, str) and isinstance(v, str) for k, v in rec.items())
    ):
        raise ModelArtifactError(f"{who}: the tag '{SHA_TAG}' is not a file -> SHA-256 record")
    return rec


def verify(folder: str | Path, expected: Mapping[str, str], who: str) -> None:
    """Check the files of a downloaded model directory against their recorded SHA-256.

    Every recorded file must exist and match, and the files this module reads (:data:`CKPT`,
    :data:`META`, :data:`MLMODEL`) must be recorded. Raises :class:`TamperedArtifactError` (one
    line naming ``who`` and the file) otherwise. Reads bytes only; deserialises nothing.
    """
    folder = Path(folder)
    unrecorded = [n for n in (MLMODEL, META, CKPT) if n not in expected]
    if unrecorded:
        raise TamperedArtifactError(
            f"{who}: no SHA-256 recorded for {', '.join(unrecorded)}; refusing to load it"
        )
    for name, sha in sorted(expected.items()):
        path = folder / name
        if ".." in Path(name).parts or not path.is_file():
            raise TamperedArtifactError(
                f"{who}: artifact file {name} is missing (recorded SHA-256 {sha[:12]}…); "
                "refusing to load it"
            )
        got = sha256_file(path)
        if got != sha:
            raise TamperedArtifactError(
                f"{who}: artifact file {name} does not match the SHA-256 recorded at registration "
                f"(recorded {sha[:12]}…, found {got[:12]}…): it was replaced or corrupted; "
                "refusing to load it"
            )


def read_flavor(folder: str | Path, who: str) -> dict[str, Any]:
    """The ``traffictwin`` flavour block of ``<folder>/MLmodel`` (YAML only, no model code).

    Raises :class:`LegacyModelError` for an ``mlflow.pytorch`` (pickled) model and
    :class:`ModelArtifactError` for anything else that is not of this flavour.
    """
    import yaml

    path = Path(folder) / MLMODEL
    if not path.is_file():
        raise ModelArtifactError(f"{who}: no {MLMODEL} file in the model artifact")
    try:
        doc = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ModelArtifactError(f"{who}: {MLMODEL} is not valid YAML ({exc})") from None
    flavors = doc.get("flavors") or {}
    block = flavors.get(FLAVOR)
    if isinstance(block, dict) and block.get("format") == ARTIFACT_FORMAT:
        return block
    if "pytorch" in flavors:
        raise LegacyModelError(
            f"{who}: logged as a pickled mlflow.pytorch model (older version); it is not loaded, "
            "since unpickling runs code — re-register it: retrain the model (`dvc repro -f` of its "
            "train stage) and run `python -m pipelines.promote`"
        )
    raise ModelArtifactError(
        f"{who}: not a '{FLAVOR}' model of format '{ARTIFACT_FORMAT}' (flavours: {sorted(flavors)})"
    )


def read_meta(folder: str | Path, who: str) -> dict[str, Any]:
    """The model's ``model_meta.json`` (JSON only)."""
    path = Path(folder) / META
    try:
        meta = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ModelArtifactError(
            f"{who}: {META} unreadable ({type(exc).__name__}: {exc})"
        ) from None
    if not isinstance(meta, dict):
        raise ModelArtifactError(f"{who}: {META} is not a JSON object")
    return meta


def save_model(
    path: str,
    mlflow_model: Any,
    *,
    files: Mapping[str, str | Path],
    problem: str,
    signature: Any = None,
    input_example: Any = None,
    sink: dict[str, Any] | None = None,
    validate_serving_input: bool = True,
) -> None:
    """MLflow flavour hook (``Model.log(flavor=this module)``): write the model directory.

    ``files``: ``{CKPT: path, META: path}`` of the local checkpoint and meta JSON to copy;
    ``input_example``: the float32 array the signature was inferred from (saved as MLflow's
    input example); ``sink`` receives ``hashes`` (SHA-256 of every file written, ``MLmodel``
    included). ``validate_serving_input`` is ``Model.log``'s own option, passed on to every
    flavour's hook; unused here.
    """
    out = Path(path)
    out.mkdir(parents=True, exist_ok=True)
    missing = {CKPT, META} - set(files)
    if missing:
        raise ModelArtifactError(f"save_model: files {sorted(missing)} are required")
    for name, src in files.items():
        if Path(name).name != name or name == MLMODEL:
            raise ModelArtifactError(f"save_model: bad artifact file name {name!r}")
        shutil.copyfile(src, out / name)
    if signature is not None:
        mlflow_model.signature = with_serving_params(signature)
    if input_example is not None:
        from mlflow.models.utils import _save_example

        _save_example(mlflow_model, input_example, str(out))
    _add_pyfunc(mlflow_model, out)
    mlflow_model.add_flavor(
        FLAVOR,
        format=ARTIFACT_FORMAT,
        problem=problem,
        checkpoint=CKPT,
        meta=META,
        files=sorted(files),
        **{VERSION_KEY: installed_version()},
    )
    mlflow_model.save(str(out / MLMODEL))
    if sink is not None:
        sink["hashes"] = file_hashes(out)


def _add_pyfunc(mlflow_model: Any, out: Path) -> None:
    """The ``python_function`` flavour: ``loader_module`` (the installed package), no code
    folder, pinned requirements (``requirements.txt``, ``python_env.yaml``, ``conda.yaml``)."""
    import mlflow.pyfunc
    from mlflow.utils.environment import (
        _CONDA_ENV_FILE_NAME,
        _PYTHON_ENV_FILE_NAME,
        _REQUIREMENTS_FILE_NAME,
        _mlflow_conda_env,
        _PythonEnv,
    )

    reqs = pip_requirements()
    (out / _REQUIREMENTS_FILE_NAME).write_text("\n".join(reqs) + "\n")
    with open(out / _CONDA_ENV_FILE_NAME, "w") as fh:
        _yaml_dump(_mlflow_conda_env(additional_pip_deps=reqs, install_mlflow=False), fh)
    _PythonEnv.current().to_yaml(str(out / _PYTHON_ENV_FILE_NAME))
    mlflow.pyfunc.add_to_model(
        mlflow_model,
        loader_module=SERVING_MODULE,
        code=None,  # never: the installed package is the served code
        conda_env=_CONDA_ENV_FILE_NAME,
        python_env=_PYTHON_ENV_FILE_NAME,
    )


def _yaml_dump(obj: Any, fh: Any) -> None:
    """Block-style YAML (as MLflow writes its environment files)."""
    import yaml

    yaml.safe_dump(obj, fh, default_flow_style=False, sort_keys=False)


def log_model(
    files: Mapping[str, str | Path],
    *,
    problem: str,
    name: str = "model",
    signature: Any = None,
    input_example: Any = None,
    metadata: Mapping[str, Any] | None = None,
) -> tuple[str, str]:
    """Log the model directory (see the module doc) to the active MLflow run.

    Returns ``(model_uri, model_id)`` of the logged model; its tag :data:`SHA_TAG` records the
    SHA-256 of every file in the directory.

    MLflow's serving-input validation is off (``validate_serving_input=False``): it reloads the
    model, compares the installed packages with its requirements, parses the JSON example (MBs
    of floats) and predicts, 3.7 s of a 6.3 s log on the ``ci`` profile, and a failure only logs a
    warning. tests/test_serving.py serves the logged example through the pyfunc and asserts the
    eager network's output instead.
    """
    import mlflow
    from mlflow.models import Model

    sink: dict[str, Any] = {}
    info = Model.log(
        None,
        name=name,
        flavor=sys.modules[__name__],
        metadata=dict(metadata) if metadata else None,
        files={k: str(v) for k, v in files.items()},
        problem=problem,
        signature=signature,
        input_example=input_example,
        sink=sink,
        validate_serving_input=False,
    )
    model_id = info.model_id
    mlflow.MlflowClient().set_logged_model_tags(model_id, {SHA_TAG: encode_hashes(sink["hashes"])})
    return info.model_uri, model_id
