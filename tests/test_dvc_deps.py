"""dvc.yaml lists, for every stage, the library code the stage's script runs: a change to any
module a stage imports (directly or through other modules) re-runs that stage."""

from __future__ import annotations

import ast
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


def closure(module: str) -> set[Path]:
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
    return {f for f in files if f is not None and not _only_docs(f)}


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


def _stages() -> dict[str, dict]:
    stages = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]
    return {name: (s["do"] if "do" in s else s) for name, s in stages.items()}


def _covered(f: Path, deps: list[str]) -> bool:
    rel = f.relative_to(ROOT).as_posix()
    return any(rel == d or rel.startswith(d.rstrip("/") + "/") for d in deps)


@pytest.mark.parametrize("stage", sorted(_stages()))
def test_stage_deps_cover_the_code_it_imports(stage: str) -> None:
    s = _stages()[stage]
    module = s["cmd"].split("python -m ")[1].split()[0]
    deps = [d if isinstance(d, str) else next(iter(d)) for d in s.get("deps", [])]
    missing = sorted(
        f.relative_to(ROOT).as_posix() for f in closure(module) if not _covered(f, deps)
    )
    assert not missing, f"dvc.yaml stage {stage} lacks deps: {missing}"
