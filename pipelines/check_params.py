"""Stage `check_params`: validate the whole of params.yaml before DVC touches any other stage.

Usage: ``python -m pipelines.check_params``. DVC removes a stage's outputs before it runs the
stage's command, and ``cache: false`` outputs (metrics, plots) cannot be checked out again: a
rejected value found by the stage itself comes too late. This stage runs first: it depends on
params.yaml as a whole and on the validation code, runs every stage's parameter checks (the same
functions the stages call at start, :data:`CHECKS`) and writes ``data/params_ok.json``, whose
content is only the schema version, so it does not change when a parameter does: every other
stage lists it as a dependency, DVC re-runs none of them for it, and a rejected value stops
``dvc repro`` / ``dvc exp run`` here, one line on stderr and exit 2, with every other stage's
outputs in place. A rejected params.yaml is not left behind either (``dvc exp run -S`` writes it
before any stage runs, and DVC does not undo that): :func:`restore_accepted` puts back the
params.yaml of the last successful check (the file whose md5 dvc.lock records for this stage's
``params.yaml`` dependency), keeping the rejected file under ``.cache/traffictwin/params/``
(docs/experiments.md). params.yaml is a file dependency, not a params dependency of every key:
dvc.lock records four lines for it instead of the whole file.
"""

from __future__ import annotations

import hashlib
import re
import subprocess
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from traffictwin.io.atomic import write_bytes_atomic, write_json_atomic

from ._common import params, run_stage
from ._paths import ROOT

#: the output every other stage depends on
OUTPUT = ROOT / "data" / "params_ok.json"
#: bumped when the output's content changes shape (never with the parameters)
SCHEMA_VERSION = 1
#: the last accepted and the last rejected params.yaml (relative to the repository; git-ignored,
#: no DVC output): what a rejection restores from, and where the rejected file is kept
KEPT = Path(".cache") / "traffictwin" / "params"


def _fusion(p: Any) -> None:
    from traffictwin.config import get
    from traffictwin.fusion.config import (
        fusion_data_config,
        fusion_eval_config,
        fusion_variants,
        grid_config,
        pose_configurations,
        registered_configurations,
        training_noise,
    )
    from traffictwin.fusion.evaluation.keys import fusion_ci_config

    get(p, "seed", int, min=0)
    grid_config(p)  # generate_fusion, prealign, train_*, evaluate_*, generate_twin
    pose_configurations(p)
    training_noise(p)
    fusion_data_config(p).params(grid_config(p))
    fusion_eval_config(p)
    fusion_ci_config(p)
    registered_configurations(p)
    fusion_variants(p)


def _fusion_model(p: Any) -> None:
    from traffictwin.config import ConfigError, typed
    from traffictwin.fusion.config import fusion_variants
    from traffictwin.fusion.model_config import FusionModelConfig

    source = "params.yaml"
    model = typed(p["fusion_model"], FusionModelConfig, key="fusion_model", source=source)
    model.deeplab_spec(source)  # train_fusion: the architecture, bounded
    model.hparams(None)
    for k, v in fusion_variants(p).items():  # a variant's loss: a registered one, with its block
        try:
            model.hparams(v.loss)
        except ConfigError as exc:
            raise ConfigError(f"{source}: 'fusion_variants.{k}.loss': {exc}") from None


def _trainer(p: Any) -> None:
    from traffictwin.trainer.settings import TrainerSettings

    # values only: whether this machine has the accelerator is the training stages' own check
    # (the paper profile's data stages run on a machine without a GPU)
    TrainerSettings.from_cfg(p, source="params.yaml")


def _registration(p: Any) -> None:
    from .train_registration import model_config

    model_config(p)


def _risk(p: Any) -> None:
    from .evaluate_risk import risk_stage_settings
    from .generate_risk import read_config
    from .train_risk import check_disparity_scale, risk_model, train_settings, variant_config
    from .train_risk_hybrid import hybrid_settings, learned_disparity

    rd, _, _ = read_config(p)  # generate_risk
    rd.sgm.check_width(rd.camera.width, what="params.yaml: 'risk_data.sgm'")  # disparity
    model = risk_model(p)
    for variant in model.variants:  # train_risk@<variant>
        cfg, _ = variant_config(model, variant)
        check_disparity_scale(p, cfg)
        train_settings(model, p, variant)
    hybrid_settings(p)  # train_risk_hybrid
    learned_disparity(p)
    risk_stage_settings(p)  # select_risk, evaluate_risk


def _stereo(p: Any) -> None:
    from .sgm_variants import variant_settings
    from .train_stereo import model_config

    variant_settings(p)  # sgm_variants
    model_config(p)  # train_stereo, train_stereo_holdout


def _twin(p: Any) -> None:
    from traffictwin.twin.config import twin_config

    twin_config(p).settings()


def _acceptance(p: Any) -> None:
    from traffictwin.acceptance import for_problem
    from traffictwin.fusion.evaluation import JUDGES
    from traffictwin.risk.evaluation import TARGET_NAMES as RISK
    from traffictwin.twin.targets import TARGET_NAMES as TWIN

    # evaluate_fusion, evaluate_risk, stereo_learned, evaluate_twin (and the report's table)
    for problem, names in (("fusion", JUDGES), ("risk", RISK), ("stereo", None), ("twin", TWIN)):
        for_problem(p, problem, names)


def _report(p: Any) -> None:
    from traffictwin.config import typed
    from traffictwin.report.config import ReportParams

    from .ablations import ablations
    from .promote import registry_config

    typed({k: p.get(k) for k in ("seed", "profile", "configurations")}, ReportParams)
    ablations(p)
    registry_config(p)


#: (what, check) in DAG order: each check calls the validators its stages call at start
CHECKS: tuple[tuple[str, Callable[[Any], None]], ...] = (
    ("fusion data and evaluation", _fusion),
    ("fusion model", _fusion_model),
    ("trainer", _trainer),
    ("registration model", _registration),
    ("risk data and models", _risk),
    ("stereo variants and network", _stereo),
    ("twin", _twin),
    ("acceptance thresholds", _acceptance),
    ("report, ablations and registry", _report),
)


def check(p: Any) -> list[str]:
    """Run every check of :data:`CHECKS` on the loaded params ``p``; the first failure raises
    a :class:`~traffictwin.config.ConfigError` naming the key (a library check's ``ValueError``
    keeps its message). Returns the checks' names."""
    from traffictwin.config import ConfigError

    for name, fn in CHECKS:
        try:
            fn(p)
        except ConfigError:
            raise
        except KeyError as exc:
            raise ConfigError(f"params.yaml: key {exc} is missing ({name})") from None
        except (TypeError, ValueError) as exc:  # a library check that names its own setting
            raise ConfigError(str(exc)) from None
    return [name for name, _ in CHECKS]


class _Yaml12Loader(yaml.SafeLoader):
    """PyYAML's safe loader that also reads YAML 1.2 floats without a dot (``1e-07``, as DVC
    writes them into dvc.lock) as floats, so the lock's values compare with params.yaml's."""


_Yaml12Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789."),
)


def _load(text: str | bytes) -> Any:
    try:
        return yaml.load(text, Loader=_Yaml12Loader)  # noqa: S506 (a safe loader)
    except yaml.YAMLError:
        return None


@dataclass(frozen=True)
class Accepted:
    """dvc.lock's record of the params.yaml the last successful check accepted: the md5 of its
    ``params.yaml`` dependency (``md5``; ``dos2unix``: a DVC 2 record without ``hash: md5``,
    hashed with CRLF read as LF), or, in a lock written while the stage listed every key of
    params.yaml as params, those values (``values``)."""

    md5: str | None = None
    dos2unix: bool = False
    values: dict[str, Any] | None = None

    def holds(self, data: bytes) -> bool:
        """Whether the params.yaml bytes ``data`` are the accepted file (same md5; for an old
        values record: the same values)."""
        if self.md5 is not None:
            hashed = data.replace(b"\r\n", b"\n") if self.dos2unix else data
            return hashlib.md5(hashed, usedforsecurity=False).hexdigest() == self.md5
        return self.values is not None and _load(data) == self.values


def accepted_params(root: Path) -> Accepted | None:
    """What the last successful check accepted, from this stage's record in ``root/dvc.lock``:
    the md5 of its ``params.yaml`` dependency, else (a lock of the earlier format) its params
    record of every key; None without either."""
    lock = root / "dvc.lock"
    if not lock.is_file():
        return None
    try:
        stage = _load(lock.read_bytes())["stages"]["check_params"]
    except (KeyError, TypeError):
        return None
    if not isinstance(stage, dict):
        return None
    for dep in stage.get("deps") or []:
        if isinstance(dep, dict) and dep.get("path") == "params.yaml":
            md5 = dep.get("md5")
            if isinstance(md5, str) and md5:
                return Accepted(md5=md5, dos2unix=dep.get("hash") != "md5")
    params = stage.get("params")
    record = params.get("params.yaml") if isinstance(params, dict) else None
    return Accepted(values=record) if isinstance(record, dict) and record else None


def _committed(root: Path) -> bytes | None:
    """``git show HEAD:params.yaml`` of ``root``, or None (no git, no commit, no such file)."""
    try:
        proc = subprocess.run(
            ["git", "show", "HEAD:./params.yaml"], cwd=root, capture_output=True, timeout=30
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return proc.stdout if proc.returncode == 0 else None


def restore_accepted(root: Path) -> str:
    """After a rejection: put params.yaml of ``root`` back to the file of the last successful
    check, byte for byte, and keep the rejected file; returns the clause for the error line
    (what happened to params.yaml).

    The accepted file is the one dvc.lock records for this stage (its md5, so a checkout of
    another commit restores that commit's parameters, never a stale copy; an older lock's
    values record works too); the bytes come from the copy the last successful check kept
    (``KEPT/accepted.yaml``) or the committed params.yaml, whichever is that file (written
    atomically). Without such a file params.yaml is left as it is."""
    path = root / "params.yaml"
    accepted = accepted_params(root)
    rejected = path.read_bytes() if path.is_file() else None
    manual = "`git checkout params.yaml` restores the committed parameters"
    if accepted is None or rejected is None:
        return (
            f"params.yaml keeps the rejected value (no accepted parameters in dvc.lock; {manual})"
        )
    if accepted.holds(rejected):  # the file the last check accepted: nothing to undo
        return "params.yaml is unchanged since the last accepted check"
    kept = root / KEPT
    for text in (_read(kept / "accepted.yaml"), _committed(root)):
        if text is not None and accepted.holds(text):
            write_bytes_atomic(kept / "rejected.yaml", rejected)
            write_bytes_atomic(path, text)
            return (
                "params.yaml restored to the parameters the last check accepted (dvc.lock); "
                f"the rejected file is kept as {KEPT / 'rejected.yaml'}"
            )
    return f"params.yaml keeps the rejected value (no copy of dvc.lock's accepted parameters; {manual})"


def _read(path: Path) -> bytes | None:
    try:
        return path.read_bytes() if path.is_file() else None
    except OSError:
        return None


def main(argv: list[str] | None = None, output: Path = OUTPUT, root: Path = ROOT) -> None:
    """Check ``root/params.yaml``; on success write ``output`` and keep a copy of the accepted
    file, on a rejection restore the last accepted one (:func:`restore_accepted`) and raise the
    check's :class:`~traffictwin.config.ConfigError` with what happened to params.yaml."""
    import argparse

    from traffictwin.config import ConfigError

    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args(argv)
    path = root / "params.yaml"
    try:
        check(params(path))
    except ConfigError as exc:
        raise ConfigError(f"{exc}; {restore_accepted(root)}") from None
    write_bytes_atomic(root / KEPT / "accepted.yaml", path.read_bytes())
    write_json_atomic(output, {"params": "params.yaml", "schema_version": SCHEMA_VERSION})


if __name__ == "__main__":
    run_stage(main, "check_params")
