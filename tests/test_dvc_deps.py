"""Every stage re-runs when a code file its script imports changes, and only then: dvc.yaml's
``stage_code`` stage depends on the code folders and writes one code manifest per script
(``stage_code/<script>.md5``: the MD5 of every file of its import closure), and every other
stage depends on its script's manifest. ``python -m pipelines.stage_deps write`` computes the lists;
these tests keep them from drifting, check that a manifest changes exactly when a file of its
closure does, and keep dvc.lock free of stages dvc.yaml no longer has."""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import pytest
import yaml
from conftest import copy_dag, run

from pipelines import stage_deps

ROOT = Path(__file__).resolve().parents[1]


def _stages() -> dict[str, dict]:
    stages = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]
    return {name: (s["do"] if "do" in s else s) for name, s in stages.items()}


def _deps(s: dict) -> list[str]:
    return [stage_deps.dep_path(d) for d in s.get("deps", [])]


def _code(s: dict) -> list[str]:
    """The code files a stage runs: its script's import closure (what its manifest lists)."""
    return stage_deps.code_deps(stage_deps.stage_module(s), ROOT)


def test_every_stage_lists_exactly_the_code_it_imports() -> None:
    diff = stage_deps.differences(ROOT / "dvc.yaml")
    assert not diff, (
        f"dvc.yaml code deps differ from the imports (stage: (missing, stale)): {diff}; "
        "run `python -m pipelines.stage_deps write`"
    )


@pytest.mark.parametrize("stage", sorted(_stages()))
def test_a_stage_depends_on_its_manifest_and_stage_code_on_the_folders_of_every_closure(
    stage: str,
) -> None:
    """A stage's only code dep is its script's manifest (a file); the ``stage_code`` stage's are
    the code folders, which hold every file of every stage's closure (so no edit escapes it)."""
    body = _stages()[stage]
    code = [d for d in _deps(body) if stage_deps.is_code(d) or stage_deps.is_manifest(d)]
    if stage != stage_deps.CODE_STAGE:
        module = stage_deps.stage_module(body)
        assert code == [stage_deps.manifest_path(module)], (stage, code)
        assert (ROOT / code[0]).is_file(), f"dvc.yaml stage {stage}: {code[0]} is not a file"
        return
    assert code == list(stage_deps.CODE_FOLDERS) and all((ROOT / d).is_dir() for d in code)
    modules = stage_deps.stage_modules(yaml.safe_load((ROOT / "dvc.yaml").read_text()))
    files = {f for m in [*modules, stage_deps.CODE_STAGE_MODULE] for f in stage_deps.code_deps(m)}
    outside = [f for f in files if not any(f.startswith(f"{d}/") for d in code)]
    assert len(files) > 100 and not outside, outside


def test_a_dropped_or_stale_dep_is_reported(tmp_path: Path) -> None:
    """The check names a code folder the ``stage_code`` stage lacks and a code file it lists
    needlessly, and a stage that lists code instead of its manifest; rewriting restores the
    lists."""
    doc = yaml.safe_load((ROOT / "dvc.yaml").read_text())
    code = doc["stages"]["stage_code"]["deps"]
    assert code == ["pipelines", "src/traffictwin"]
    code.remove("src/traffictwin")
    code.append("pipelines/reset.py")  # inside a folder it already lists
    deps = doc["stages"]["train_risk"]["do"]["deps"]
    assert deps[0] == "stage_code/train_risk.md5"
    deps[0] = "src/traffictwin/risk/dave2.py"
    broken = tmp_path / "dvc.yaml"
    broken.write_text(yaml.safe_dump(doc, sort_keys=False))
    (tmp_path / "params.yaml").write_text((ROOT / "params.yaml").read_text())
    diff = stage_deps.differences(broken)
    assert diff == {
        "stage_code": (["src/traffictwin"], ["pipelines/reset.py"]),
        "train_risk": (["stage_code/train_risk.md5"], ["src/traffictwin/risk/dave2.py"]),
    }
    assert stage_deps.write(broken) == ["stage_code", "train_risk"]
    assert stage_deps.differences(broken) == {}
    # data deps survive the rewrite, after the code
    rewritten = yaml.safe_load(broken.read_text())["stages"]["train_risk"]["do"]["deps"]
    assert rewritten[0] == "stage_code/train_risk.md5"
    assert rewritten[1:] == [d for d in deps if not stage_deps.is_code(d)]


def _tree(root: Path) -> None:
    """Two stage scripts sharing one module, and a dvc.yaml that runs them."""
    pkg = root / "src" / "traffictwin"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text('"""docs only."""\n')
    (pkg / "shared.py").write_text("X = 1\n")
    (pkg / "only_b.py").write_text("")
    (root / "pipelines").mkdir()
    (root / "pipelines" / "a.py").write_text("from traffictwin import shared\n")
    (root / "pipelines" / "b.py").write_text("from traffictwin import shared, only_b\n")
    stages = {
        "stage_code": {"cmd": "python -m pipelines.stage_deps manifests", "deps": [], "outs": []},
        "a": {"cmd": "python -m pipelines.a", "deps": ["data/in"]},
        "b": {"foreach": [1, 2], "do": {"cmd": "python -m pipelines.b --n ${item}", "deps": []}},
    }
    (root / "dvc.yaml").write_text(yaml.safe_dump({"stages": stages}, sort_keys=False))
    (root / "params.yaml").write_text("seed: 1\n")


def test_manifests_are_md5sum_lines_of_the_closure_and_change_with_it(tmp_path: Path) -> None:
    _tree(tmp_path)
    assert stage_deps.write(tmp_path / "dvc.yaml") == ["stage_code", "a", "b"]
    doc = yaml.safe_load((tmp_path / "dvc.yaml").read_text())["stages"]
    assert doc["a"]["deps"] == ["stage_code/a.md5", "data/in"]
    assert doc["b"]["do"]["deps"] == ["stage_code/b.md5"]
    assert doc["stage_code"]["outs"] == [
        {"stage_code/a.md5": {"cache": False}},
        {"stage_code/b.md5": {"cache": False}},
    ]
    assert doc["stage_code"]["deps"] == ["pipelines", "src/traffictwin"]
    assert stage_deps.write_manifests(tmp_path / "dvc.yaml") == [
        "stage_code/a.md5",
        "stage_code/b.md5",
    ]
    md5_x1 = "67febd88df9610701ace8ce092f0eb6b"  # `printf "X = 1\\n" | md5sum`
    assert hashlib.md5(b"X = 1\n").hexdigest() == md5_x1
    md5_empty = "d41d8cd98f00b204e9800998ecf8427e"
    md5_a = hashlib.md5(b"from traffictwin import shared\n").hexdigest()
    assert (tmp_path / "stage_code" / "a.md5").read_text() == (
        f"{md5_a}  pipelines/a.py\n{md5_x1}  src/traffictwin/shared.py\n"
    )
    assert (
        f"{md5_empty}  src/traffictwin/only_b.py\n" in (tmp_path / "stage_code/b.md5").read_text()
    )
    assert stage_deps.write_manifests(tmp_path / "dvc.yaml") == []  # nothing changed: untouched
    # an edit changes exactly the manifests of the scripts that import the file
    (tmp_path / "src" / "traffictwin" / "only_b.py").write_text("Y = 2\n")
    (tmp_path / "stage_code" / "gone.md5").write_text("")  # a script no stage runs any more
    assert stage_deps.write_manifests(tmp_path / "dvc.yaml") == [
        "stage_code/b.md5",
        "stage_code/gone.md5",
    ]
    assert not (tmp_path / "stage_code" / "gone.md5").exists()


def test_closure_follows_imports_inside_functions_and_parent_packages(tmp_path: Path) -> None:
    pkg = tmp_path / "src" / "traffictwin"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text('"""docs only."""\n__version__ = "1"\n')
    (pkg / "sub" / "__init__.py").write_text("from . import b\n")
    (pkg / "sub" / "a.py").write_text("def f():\n    from traffictwin import c\n")
    (pkg / "sub" / "b.py").write_text("")
    (pkg / "c.py").write_text("")
    (pkg / "unused.py").write_text("")
    files = stage_deps.closure("traffictwin.sub.a", tmp_path)
    got = sorted(p.relative_to(tmp_path).as_posix() for p in files)
    assert got == [  # the docs-only traffictwin/__init__ runs nothing: left out
        "src/traffictwin/c.py",
        "src/traffictwin/sub/__init__.py",
        "src/traffictwin/sub/a.py",
        "src/traffictwin/sub/b.py",
    ]


def test_closure_holds_the_templates_a_module_renders(tmp_path: Path) -> None:
    pkg = tmp_path / "src" / "traffictwin"
    (pkg / "page" / "templates").mkdir(parents=True)
    (pkg / "page" / "templates" / "a.md.j2").write_text("{{ x }}\n")
    (pkg / "page" / "templates" / "notes.txt").write_text("not a template\n")
    (pkg / "page" / "render.py").write_text(
        'NAME = "a.md.j2"\nfrom traffictwin.page import plain\n'
    )
    (pkg / "page" / "plain.py").write_text("X = 1\n")
    got = sorted(
        p.relative_to(tmp_path).as_posix()
        for p in stage_deps.closure("traffictwin.page.render", tmp_path)
    )
    assert got == [
        "src/traffictwin/page/plain.py",
        "src/traffictwin/page/render.py",
        "src/traffictwin/page/templates/a.md.j2",
    ]
    plain = stage_deps.closure("traffictwin.page.plain", tmp_path)  # renders nothing: no template
    assert sorted(p.name for p in plain) == ["plain.py"]


def test_report_code_retrains_and_regenerates_nothing() -> None:
    """Editing the report's page kit or a report section re-runs only the stages that render the
    report: no data, training or evaluation stage imports them."""
    report_only = ("src/traffictwin/report/", "report_section", "report_tables", "findings_")
    kit = ("src/traffictwin/report/colours.py", "src/traffictwin/report/prose.py")
    for name, s in _stages().items():
        if name in ("report", "plot_data", "check_params", stage_deps.CODE_STAGE):
            continue
        hits = [
            d
            for d in _code(s)
            if any(k in d for k in report_only) and d not in kit  # figure colours, finding prose
        ]
        assert not hits, f"stage {name} depends on report code {hits}"


#: the stages that make data or train a model: the expensive ones
DATA_AND_TRAINING = (
    "generate_fusion",
    "prealign",
    "prealign_mixed",
    "register",
    "generate_risk",
    "disparity",
    "orb_filter",
    "generate_twin",
    "train_fusion",
    "train_fusion_variant",
    "train_registration",
    "train_risk",
    "train_risk_hybrid",
    "train_stereo",
    "train_stereo_holdout",
)
#: what evaluation alone uses: the fusion methods compared (the twin methods are not here: the
#: twin's config, which generate_twin reads, checks their names)
EVALUATION_ONLY = ("src/traffictwin/fusion/methods.py",)
#: the one stage that draws figures: every chart and figure of the run
DRAWING = ("plot_data",)


def _figure_modules() -> list[str]:
    """Every figure module: ``figures.py``, ``*_figures.py``, ``*_figure.py`` under src/traffictwin."""
    src = ROOT / "src" / "traffictwin"
    pats = ("figures.py", "*_figures.py", "*_figure.py")
    return sorted({p.relative_to(ROOT).as_posix() for pat in pats for p in src.rglob(pat)})


def test_a_figure_edit_reruns_only_the_stages_that_draw() -> None:
    """Editing any figure (of the data, a learning curve or an evaluation) re-runs plot_data (and
    the report), never a data, training or evaluation stage."""
    stages, figures = _stages(), _figure_modules()
    for f in ("fusion/data_figure.py", "fusion/figures.py", "twin/figures.py", "risk/figures.py"):
        assert f"src/traffictwin/{f}" in figures
    for name, s in stages.items():
        if name in (*DRAWING, stage_deps.CODE_STAGE):
            continue
        hits = [d for d in _code(s) if d in figures]
        assert not hits, f"stage {name} depends on figure code {hits}"
    drawn = {d for n in DRAWING for d in _code(stages[n])}
    assert set(figures) <= drawn, set(figures) - drawn


def test_a_new_method_regenerates_and_retrains_nothing() -> None:
    """Adding a method to fusion/methods.py re-runs the evaluations, never a data or training
    stage."""
    stages = _stages()
    assert set(DATA_AND_TRAINING) <= set(stages), set(DATA_AND_TRAINING) - set(stages)
    for name in DATA_AND_TRAINING:
        hits = [d for d in _code(stages[name]) if d in EVALUATION_ONLY]
        assert not hits, f"stage {name} depends on evaluation-only code {hits}"
    assert all((ROOT / f).is_file() for f in EVALUATION_ONLY)
    assert "src/traffictwin/fusion/methods.py" in _code(stages["evaluate_fusion"])


def test_dvc_lock_holds_only_todays_stages() -> None:
    stale = stage_deps.stale_lock_stages(ROOT / "dvc.yaml", ROOT / "dvc.lock")
    assert not stale, f"dvc.lock has stages dvc.yaml no longer defines: {stale}"


def test_prune_lock_removes_only_stale_stages(tmp_path: Path) -> None:
    for name in ("dvc.yaml", "params.yaml"):
        (tmp_path / name).write_text((ROOT / name).read_text())
    lock = yaml.safe_load((ROOT / "dvc.lock").read_text())
    # three of today's stages as the lock records them (a round trip of the whole lock takes
    # seconds and tests nothing more)
    kept = dict(list(lock["stages"].items())[:3])
    lock["stages"] = dict(kept)
    lock["stages"]["train_fusion@Z"] = {"cmd": "python -m pipelines.train_fusion"}
    (tmp_path / "dvc.lock").write_text(yaml.safe_dump(lock, sort_keys=False))
    assert stage_deps.prune_lock(tmp_path / "dvc.yaml", tmp_path / "dvc.lock") == ["train_fusion@Z"]
    assert yaml.safe_load((tmp_path / "dvc.lock").read_text())["stages"] == kept
    assert stage_deps.prune_lock(tmp_path / "dvc.yaml", tmp_path / "dvc.lock") == []


def _status_after_edit(repo: Path, rel: str) -> set[str]:
    """The stages ``dvc status`` lists after appending a comment to ``rel`` and writing the code
    manifests, in the finished DAG ``repo``: the ``stage_code`` stage's command, run without
    ``dvc repro`` (a second DVC process per edit), so ``stage_code`` itself, whose code deps
    changed, is left out of the answer."""
    with (repo / rel).open("a") as f:
        f.write("# an edit that changes no behaviour\n")
    code_stage = stage_deps.CODE_STAGE
    assert _stages()[code_stage]["cmd"] == f"python -m {stage_deps.CODE_STAGE_MODULE} manifests"
    run([sys.executable, "-m", stage_deps.CODE_STAGE_MODULE, "manifests"], repo)
    status = json.loads(run(["dvc", "status", "--json"], repo).stdout or "{}")
    assert code_stage in status, status  # DVC sees the edit
    return {name.split("@")[0] for name in status} - {code_stage}  # a foreach stage as its template


def test_an_edit_re_runs_only_the_stages_that_import_it(ci_dag: Path, tmp_path: Path) -> None:
    """End to end on the finished ci DAG: after a report edit only ``report`` is out of date, after
    a new fusion method only the stages that import fusion/methods.py (evaluations, never a data
    or training stage), after a learning-curve, data-figure or evaluation-figure edit only
    ``plot_data``."""
    repo = copy_dag(ci_dag, tmp_path / "repo", mlflow=False)
    # byte-compiled code beside the sources is no edit (.dvcignore): nothing is out of date
    for folder in stage_deps.CODE_FOLDERS:
        cache = repo / folder / "__pycache__"
        cache.mkdir(exist_ok=True)
        (cache / "new_module.cpython-311.pyc").write_bytes(b"\x00")
    (repo / "src/traffictwin/fusion/stray.pyc").write_bytes(b"\x00")
    assert json.loads(run(["dvc", "status", "--json"], repo).stdout or "{}") == {}
    assert _status_after_edit(repo, "src/traffictwin/report/render.py") == {"report"}
    # the edits add up: each status also lists the stages the edits before made stale
    drawn = {"report", "plot_data"}
    assert _status_after_edit(repo, "src/traffictwin/fusion/training_figures.py") == drawn
    assert _status_after_edit(repo, "src/traffictwin/risk/data_figures.py") == drawn
    assert _status_after_edit(repo, "src/traffictwin/twin/figures.py") == drawn
    assert _status_after_edit(repo, "src/traffictwin/risk/figures.py") == drawn
    stale = _status_after_edit(repo, "src/traffictwin/fusion/methods.py")
    importers = {
        name for name, s in _stages().items() if "src/traffictwin/fusion/methods.py" in _code(s)
    }
    assert "evaluate_fusion" in stale and not stale & set(DATA_AND_TRAINING), stale
    assert stale <= importers | drawn, stale - importers
