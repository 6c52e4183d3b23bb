"""dvc.yaml lists, for every stage, exactly the code files its script imports (directly or through
other modules), one file each: a change to a module re-runs the stages that import it, and only
those. ``python -m pipelines.stage_deps write`` computes the lists; these tests keep them from
drifting, and keep dvc.lock free of stages dvc.yaml no longer has."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from pipelines import stage_deps

ROOT = Path(__file__).resolve().parents[1]


def _stages() -> dict[str, dict]:
    stages = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]
    return {name: (s["do"] if "do" in s else s) for name, s in stages.items()}


def _deps(s: dict) -> list[str]:
    return [stage_deps.dep_path(d) for d in s.get("deps", [])]


def test_every_stage_lists_exactly_the_code_it_imports() -> None:
    diff = stage_deps.differences(ROOT / "dvc.yaml")
    assert not diff, (
        f"dvc.yaml code deps differ from the imports (stage: (missing, stale)): {diff}; "
        "run `python -m pipelines.stage_deps write`"
    )


@pytest.mark.parametrize("stage", sorted(_stages()))
def test_code_deps_are_files_never_folders(stage: str) -> None:
    for dep in filter(stage_deps.is_code, _deps(_stages()[stage])):
        assert (ROOT / dep).is_file(), f"dvc.yaml stage {stage}: {dep} is not a file"


def test_a_dropped_or_stale_dep_is_reported(tmp_path: Path) -> None:
    """The check names a module a stage imports but does not list, and a listed one it does not
    import; rewriting restores the list."""
    doc = yaml.safe_load((ROOT / "dvc.yaml").read_text())
    deps = doc["stages"]["train_risk"]["do"]["deps"]
    assert "src/traffictwin/risk/dave2.py" in deps
    deps.remove("src/traffictwin/risk/dave2.py")
    deps.append("src/traffictwin/fusion/deeplab.py")
    broken = tmp_path / "dvc.yaml"
    broken.write_text(yaml.safe_dump(doc, sort_keys=False))
    (tmp_path / "params.yaml").write_text((ROOT / "params.yaml").read_text())
    diff = stage_deps.differences(broken, root=ROOT)
    assert diff == {
        "train_risk": (["src/traffictwin/risk/dave2.py"], ["src/traffictwin/fusion/deeplab.py"])
    }
    assert stage_deps.write(broken, root=ROOT) == ["train_risk"]
    assert stage_deps.differences(broken, root=ROOT) == {}
    # data deps survive the rewrite, after the code
    rewritten = yaml.safe_load(broken.read_text())["stages"]["train_risk"]["do"]["deps"]
    assert [d for d in rewritten if not stage_deps.is_code(d)] == [
        d for d in deps if not stage_deps.is_code(d)
    ]


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
        if name in ("report", "plot_data", "check_params"):
            continue
        hits = [
            d
            for d in _deps(s)
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
#: what evaluation alone uses: the fusion methods compared and the evaluation figures (the twin
#: methods are not here: the twin's config, which generate_twin reads, checks their names)
EVALUATION_ONLY = (
    "src/traffictwin/fusion/methods.py",
    "src/traffictwin/fusion/figures.py",
    "src/traffictwin/fusion/map_figures.py",
    "src/traffictwin/twin/figures.py",
    "src/traffictwin/risk/figures.py",
)


def test_a_new_method_or_evaluation_figure_regenerates_and_retrains_nothing() -> None:
    """Adding a method to fusion/methods.py or editing an evaluation figure re-runs the
    evaluations, never a data or training stage."""
    stages = _stages()
    assert set(DATA_AND_TRAINING) <= set(stages), set(DATA_AND_TRAINING) - set(stages)
    for name in DATA_AND_TRAINING:
        hits = [d for d in _deps(stages[name]) if d in EVALUATION_ONLY]
        assert not hits, f"stage {name} depends on evaluation-only code {hits}"
    assert all((ROOT / f).is_file() for f in EVALUATION_ONLY)
    assert "src/traffictwin/fusion/methods.py" in _deps(stages["evaluate_fusion"])


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
