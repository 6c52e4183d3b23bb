"""Start-up cost: the stages that train nothing, the CLI's entry module and its help and argument
errors import no Lightning (~4-9 s a process), and those that run no network import no torch (the
CLI's no matplotlib either); no stage imports MLflow at import time; the parameter check (the first stage of every `dvc repro`)
imports none of torch, Lightning, MLflow or matplotlib.

One subprocess imports the modules in phases (torch-free first, then Lightning-free), each phase
checked before the next, so a heavy import in an early module cannot hide behind a later one.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: stage scripts that import Lightning when imported (the only ones that may; the other training
#: stages import their training code in ``main``, so check_params can read their settings)
TRAINING = {"train_fusion"}
#: stage scripts that load or run a torch network at import time (the others, the training and
#: evaluation stages that check_params imports for their settings among them, import torch in the
#: functions that use it)
TORCH = TRAINING | {"select_risk"}
#: library modules the evaluation stages and the CLI load networks and data through
LIGHT_LIBRARY = (
    "traffictwin.trainer.settings",
    "traffictwin.trainer.sampling",
    "traffictwin.fusion.registration_io",
    "traffictwin.risk.stereo_io",
    "traffictwin.risk.source",
)
#: CLI invocations that end in argparse (help or a usage error) before any work
CLI_ARGS = (["--help"], ["fuse", "--help"], ["risk", "--help"], ["twin"], ["--no-such-option"])

_PROBE = r"""
import contextlib, importlib, io, json, sys

def heavy():
    return sorted(m for m in ("torch", "lightning", "mlflow", "matplotlib") if m in sys.modules)

phases = json.loads(sys.argv[1])
out = {}
for name, modules, cli_args in phases:
    for m in modules:
        importlib.import_module(m)
    if cli_args:
        from traffictwin.cli import main

        for args in cli_args:
            sink = io.StringIO()
            with contextlib.redirect_stdout(sink), contextlib.redirect_stderr(sink):
                try:
                    main(args)
                except SystemExit:
                    pass
    out[name] = heavy()
print(json.dumps(out))
"""


def _fresh_python(code: str, *args: str) -> subprocess.CompletedProcess:
    """``code`` run by a new Python process in the repository root (nothing imported yet)."""
    return subprocess.run(
        [sys.executable, "-c", code, *args], capture_output=True, text=True, cwd=ROOT, check=False
    )


def _stages() -> list[str]:
    """Every stage script of pipelines/ (no helper module starting with an underscore)."""
    names = sorted(p.stem for p in (ROOT / "pipelines").glob("*.py"))
    return [n for n in names if not n.startswith("_")]


def test_stages_that_train_nothing_import_no_lightning_and_the_cli_no_torch() -> None:
    stages = _stages()
    assert TORCH <= set(stages), f"stage scripts missing from pipelines/: {TORCH - set(stages)}"
    cli = ["traffictwin.cli", "traffictwin.cli.__main__"]
    torch_free = [f"pipelines.{s}" for s in stages if s not in TORCH]
    lightning_free = list(LIGHT_LIBRARY) + [
        f"pipelines.{s}" for s in stages if s in TORCH - TRAINING
    ]
    phases = [  # the CLI's argparse paths first, then torch-free, then Lightning-free
        ("cli", cli, [list(a) for a in CLI_ARGS]),
        ("torch_free", torch_free, []),
        ("lightning_free", lightning_free, []),
    ]
    r = _fresh_python(_PROBE, json.dumps(phases))
    assert r.returncode == 0, r.stderr[-2000:]
    got = json.loads(r.stdout.strip().splitlines()[-1])
    assert got["cli"] == [], (
        f"importing {cli} and running traffictwin {CLI_ARGS} (help, usage errors) loaded "
        f"{got['cli']}: a module-level import of torch, Lightning, MLflow or matplotlib crept "
        "into the CLI's argument parsing (import it where it is used)"
    )
    # stages that draw figures may import matplotlib; none of them torch, Lightning or MLflow
    stage_heavy = [m for m in got["torch_free"] if m != "matplotlib"]
    assert stage_heavy == [], (
        f"importing {torch_free} loaded {stage_heavy}: a module-level import of torch, Lightning "
        "or MLflow crept into a stage that runs no network (import it where it is used)"
    )
    assert "lightning" not in got["lightning_free"] and "mlflow" not in got["lightning_free"], (
        f"importing {lightning_free} loaded {got['lightning_free']}: only the training stages "
        f"({sorted(TRAINING)}) may import Lightning"
    )


#: what the parameter check must not import: torch (~3-4 s a process on 2 cores), Lightning
#: (~4-9 s), MLflow, matplotlib (~1 s), pandas (~0.6 s)
CHECK_FREE = ("torch", "lightning", "torchmetrics", "mlflow", "matplotlib", "pandas")


def test_the_parameter_check_runs_without_torch_lightning_mlflow_or_matplotlib() -> None:
    """``check_params`` runs first in every `dvc repro` and `dvc exp run`: it validates every
    group (the networks' settings and architectures included) without torch, Lightning, MLflow,
    matplotlib or pandas: the settings and spec classes live apart from the networks and the
    training code (``fusion.deeplab_spec``, ``stereo.network_spec``, ``risk.dave2_config``, ...),
    the stages it imports for their settings load their figures, models and networks in ``main``,
    and the modules it reads settings from build their tables (pandas) inside functions."""
    probe = (
        "import json, sys\n"
        "from pathlib import Path\n"
        "import pipelines.check_params as c\n"
        "names = c.check(c.params(Path('params.yaml')))\n"
        f"print(json.dumps([names, sorted(m for m in {CHECK_FREE!r} if m in sys.modules)]))\n"
    )
    r = _fresh_python(probe)
    assert r.returncode == 0, r.stderr[-2000:]
    names, heavy = json.loads(r.stdout.strip().splitlines()[-1])
    assert len(names) >= 6, names  # every group's check ran
    assert heavy == [], (
        f"check_params loaded {heavy}: a spec or settings class moved back beside its network or "
        "training, or a stage it imports for its settings imports its figures or models at "
        "module level (import them in main)"
    )


def test_a_stage_failing_before_any_training_imports_no_lightning() -> None:
    """The stage wrapper's error matching (``run_stage``: evaluated on every exception, an
    argparse usage error too) loads no Lightning where none was loaded: a light stage's one-line
    error comes without the ~8 s import."""
    probe = (
        "import sys\n"
        "from pipelines._common import run_stage\n"
        "def main():\n"
        "    raise ValueError('params.yaml: bad value')\n"
        "try:\n"
        "    run_stage(main, 'unit_stage')\n"
        "except SystemExit as exc:\n"
        "    print(exc.code, 'lightning' in sys.modules)\n"
    )
    r = _fresh_python(probe)
    assert r.stderr.strip() == "unit_stage: error: ValueError: params.yaml: bad value", r.stderr
    assert r.stdout.split() == ["2", "False"], r.stdout
