"""dvc.yaml lists, for every stage, the library code the stage's script runs: a change to any
module a stage imports (directly or through other modules) re-runs that stage.

A dep is a module file or a package folder (``src/traffictwin/<package>``: DVC hashes a folder as a
whole, so it covers every file under it); never a whole tree (``src/traffictwin``, ``pipelines``),
which would re-run every stage on any change. No code dep is stale: a listed module is imported, a
listed folder holds a module the stage imports."""

from __future__ import annotations

import ast
from functools import cache
from pathlib import Path

import pytest
import yaml
from _imports import imported_names

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src"


def _module_file(mod: str) -> Path | None:
    base = (SRC if mod.startswith("traffictwin") else ROOT) / mod.replace(".", "/")
    for p in (base.with_suffix(".py"), base / "__init__.py"):
        if p.exists():
            return p
    return None


def _imports(path: Path) -> set[str]:
    """Modules of traffictwin / pipelines that ``path`` imports (anywhere in the file)."""
    package = ".".join(
        path.relative_to(SRC if SRC in path.parents else ROOT).with_suffix("").parts[:-1]
    )
    return {
        n
        for n in imported_names(ast.parse(path.read_text()), package)
        if n.split(".")[0] in ("traffictwin", "pipelines") and _module_file(n)
    }


@cache
def closure(module: str) -> frozenset[Path]:
    """Files of every traffictwin/pipelines module ``module`` needs, transitively."""
    seen: set[str] = set()
    todo = [module]
    while todo:
        m = todo.pop()
        if m in seen:
            continue
        seen.add(m)
        f = _module_file(m)
        if f is not None:
            todo += sorted(_imports(f) - seen)
            parts = m.split(".")  # importing a.b.c runs a/__init__ and a/b/__init__ too
            todo += [".".join(parts[:i]) for i in range(1, len(parts))]
    files = {_module_file(m) for m in seen}
    return frozenset(f for f in files if f is not None and not _only_docs(f))


def _only_docs(f: Path) -> bool:
    """A package ``__init__`` with nothing but a docstring and ``__version__`` runs no stage code."""
    if f.name != "__init__.py":
        return False
    body = ast.parse(f.read_text()).body
    return all(
        (isinstance(n, ast.Expr) and isinstance(n.value, ast.Constant))
        or (
            isinstance(n, ast.Assign)
            and [getattr(t, "id", "") for t in n.targets] == ["__version__"]
        )
        for n in body
    )


@cache
def _stages() -> dict[str, dict]:
    stages = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]
    return {name: (s["do"] if "do" in s else s) for name, s in stages.items()}


def _covered(f: Path, deps: list[str]) -> bool:
    rel = f.relative_to(ROOT).as_posix()
    return any(rel == d or rel.startswith(d.rstrip("/") + "/") for d in deps)


def _deps(s: dict) -> list[str]:
    return [d if isinstance(d, str) else next(iter(d)) for d in s.get("deps", [])]


def _module(s: dict) -> str:
    return s["cmd"].split("python -m ")[1].split()[0]


def _missing(module: str, deps: list[str]) -> list[str]:
    """Files of ``module``'s import closure that no dep in ``deps`` covers."""
    return sorted(f.relative_to(ROOT).as_posix() for f in closure(module) if not _covered(f, deps))


def _code(dep: str) -> bool:
    return dep.split("/")[0] in ("src", "pipelines")


@pytest.mark.parametrize("stage", sorted(_stages()))
def test_stage_deps_cover_the_code_it_imports(stage: str) -> None:
    s = _stages()[stage]
    missing = _missing(_module(s), _deps(s))
    assert not missing, f"dvc.yaml stage {stage} lacks deps: {missing}"


@pytest.mark.parametrize("stage", sorted(_stages()))
def test_stage_code_deps_are_modules_or_package_folders_it_imports(stage: str) -> None:
    s = _stages()[stage]
    needed = {f.relative_to(ROOT).as_posix() for f in closure(_module(s))}
    for dep in filter(_code, _deps(s)):
        path = ROOT / dep
        assert path.exists(), f"dvc.yaml stage {stage}: {dep} does not exist"
        if path.is_dir():
            parts = Path(dep).parts
            assert len(parts) == 3 and parts[:2] == ("src", "traffictwin"), (
                f"dvc.yaml stage {stage}: {dep} is not a package folder src/traffictwin/<package>"
            )
            assert any(n.startswith(dep.rstrip("/") + "/") for n in needed), (
                f"dvc.yaml stage {stage}: imports nothing of {dep}"
            )
        else:
            assert dep in needed, f"dvc.yaml stage {stage}: does not import {dep} (stale dep)"


def test_a_module_no_dep_covers_is_reported() -> None:
    """The check fails when a stage imports a module its deps do not cover (a folder covers its
    files, a sibling file does not)."""
    s = _stages()["train_risk"]
    deps = _deps(s)
    assert _missing(_module(s), deps) == []
    dropped = [d for d in deps if d != "src/traffictwin/risk/dave2.py"]
    assert _missing(_module(s), dropped) == ["src/traffictwin/risk/dave2.py"]
    as_folder = [d for d in dropped if not d.startswith("src/traffictwin/risk/")]
    assert _missing(_module(s), [*as_folder, "src/traffictwin/risk"]) == []
    assert "src/traffictwin/risk/dave2.py" in _missing(
        _module(s), [*as_folder, "src/traffictwin/ri"]
    )
