"""The house rules, checked on the source: no import cycles, one-way layers, a library that knows
nothing of the workflow layer (no params.yaml, no pipelines, no subprocess)."""

from __future__ import annotations

import ast
import functools
from pathlib import Path

import pytest

from pipelines.stage_deps import imported_names

SRC = Path(__file__).resolve().parents[1] / "src"
PKG = "traffictwin"

# cli -> twin -> fusion, risk -> report (page kit), evidential, stereo, sim, stats, io, mlops, ...
# (the report stage composes the problems' section providers; report/ itself knows no problem).
# The twin is where the two problems meet: it composes fusion's registrations and combinations
# and risk's corridor metric, so it sits one layer above them (neither may import it).
PROBLEMS = {"fusion", "risk"}
COMPOSITE = {"twin"}
TOP = {"cli", "api", "export"}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(SRC).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _modules() -> dict[str, ast.Module]:
    return {
        _module_name(p): ast.parse(p.read_text(), str(p)) for p in sorted((SRC / PKG).rglob("*.py"))
    }


def _imports(name: str, tree: ast.Module, known: set[str]) -> set[str]:
    """Every traffictwin module ``name`` imports, at module level or inside functions."""
    is_pkg = any(k.startswith(name + ".") for k in known)
    package = name if is_pkg else name.rpartition(".")[0]
    out: set[str] = set()
    for t in imported_names(tree, package):
        while t and t not in known:
            t = t.rpartition(".")[0]
        if t and t != name and t.startswith(PKG):
            out.add(t)
    return out


@functools.cache
def _import_graph() -> tuple[tuple[str, frozenset[str]], ...]:
    mods = MODULES  # parsed once, at collection
    known = set(mods)
    return tuple((m, frozenset(_imports(m, t, known) - {PKG})) for m, t in mods.items())


def _graph() -> dict[str, set[str]]:
    """``{module: the traffictwin modules it imports}``, parsed once per test process (a fresh
    copy each call)."""
    return {m: set(deps) for m, deps in _import_graph()}


def _find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(n: str) -> list[str] | None:
        state[n] = 1
        stack.append(n)
        for m in sorted(graph.get(n, ())):
            if state.get(m) == 1:
                return stack[stack.index(m) :] + [m]
            if m not in state and (c := visit(m)):
                return c
        stack.pop()
        state[n] = 2
        return None

    for n in sorted(graph):
        if n not in state and (c := visit(n)):
            return c
    return None


def test_cycle_finder_finds_a_cycle() -> None:
    assert _find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _find_cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None


def test_import_graph_has_no_cycle() -> None:
    graph = _graph()
    assert len(graph) > 30, "the scan found too few modules"
    assert _find_cycle(graph) is None, f"import cycle: {' -> '.join(_find_cycle(graph) or [])}"


def _room(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def test_layers_point_one_way() -> None:
    """Shared foundations never import a problem, problems never import each other, the twin or
    the top; the twin imports the problems but never the top."""
    bad = []
    for mod, deps in _graph().items():
        room = _room(mod)
        for d in deps:
            droom = _room(d)
            if droom == room:
                continue
            if room not in PROBLEMS | COMPOSITE | TOP and droom in PROBLEMS | COMPOSITE | TOP:
                bad.append(f"{mod} (foundation) imports {d}")
            elif room in PROBLEMS and droom in PROBLEMS | COMPOSITE | TOP:
                bad.append(f"{mod} ({room}) imports {d}")
            elif room in COMPOSITE and droom in TOP:
                bad.append(f"{mod} ({room}) imports {d}")
    assert not bad, "\n".join(sorted(bad))


# modules below sim/ and evidential/ (pose maths, scan data) and the nested-key lookup (below the
# report, the findings and the dataset manifests): they import nothing of the package
LEAVES = ("traffictwin.geometry", "traffictwin.scan", "traffictwin.nested")


def test_evidential_never_imports_sim() -> None:
    """Pose maths and scan data live below both (``geometry.py``, ``scan.py``), so the
    evidential maths work on any source of scans and poses, not only the simulator's."""
    bad = sorted(
        f"{mod} imports {d}"
        for mod, deps in _graph().items()
        if _room(mod) == "evidential"
        for d in deps
        if _room(d) == "sim"
    )
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("leaf", LEAVES)
def test_leaf_modules_import_nothing_of_the_package(leaf: str) -> None:
    graph = _graph()
    assert leaf in graph, f"{leaf} not found"
    assert graph[leaf] == set(), f"{leaf} imports {sorted(graph[leaf])}"


def _params_file_uses(tree: ast.Module) -> list[int]:
    """Lines where a string naming params.yaml is opened or used as a path: an argument of a call,
    an operand of ``/``, or the default of a parameter whose name says it is a path. (Labels in
    error messages, e.g. ``source="params.yaml"``, and docstrings are not uses.)"""

    def names_params(n: ast.AST) -> bool:
        # a file name, not a message that mentions the file ("params.yaml: 'grid' must be ...")
        return (
            isinstance(n, ast.Constant)
            and isinstance(n.value, str)
            and (n.value == "params.yaml" or n.value.endswith("/params.yaml"))
        )

    lines = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and any(names_params(a) for a in node.args):
            lines.append(node.lineno)
        elif isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div):
            if names_params(node.left) or names_params(node.right):
                lines.append(node.lineno)
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            a = node.args
            pos = a.posonlyargs + a.args
            pairs = list(zip(pos[len(pos) - len(a.defaults) :], a.defaults))
            pairs += [(k, d) for k, d in zip(a.kwonlyargs, a.kw_defaults) if d is not None]
            lines += [d.lineno for arg, d in pairs if "path" in arg.arg and names_params(d)]
    return lines


MODULES = _modules()


@pytest.mark.parametrize("name", sorted(MODULES))
def test_library_knows_nothing_of_the_workflow_layer(name: str) -> None:
    tree = MODULES[name]
    imported = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    imported |= {
        n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and not n.level
    }
    assert not any(m == "pipelines" or m.startswith("pipelines.") for m in imported), (
        f"{name} imports pipelines"
    )
    assert "subprocess" not in imported, f"{name} runs a subprocess"
    uses = _params_file_uses(tree)
    assert not uses, f"{name} opens params.yaml (lines {uses}): the workflow layer passes values"


def test_params_file_check_sees_opens() -> None:
    tree = ast.parse(
        'def f(path="params.yaml", source="params.yaml"):\n    open("params.yaml")\n    return root / "params.yaml"\n'
    )
    assert _params_file_uses(tree) == [1, 2, 3]
