"""The risk problem's house: one-way imports (no cycles) between risk/, stereo/ and sim/."""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "traffictwin"
PACKAGES = ("risk", "stereo", "sim")


def _graph() -> dict[str, set[str]]:
    """Module -> the traffictwin modules it imports (top level or inside functions)."""
    mods = {
        "traffictwin." + ".".join(p.relative_to(SRC).with_suffix("").parts): p
        for pkg in PACKAGES
        for p in (SRC / pkg).glob("*.py")
        if p.name != "__init__.py"
    }
    graph: dict[str, set[str]] = {}
    for mod, path in mods.items():
        deps: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module:
                deps.add(node.module)
                deps.update(f"{node.module}.{a.name}" for a in node.names)
            elif isinstance(node, ast.Import):
                deps.update(a.name for a in node.names)
        graph[mod] = {d for d in deps if d in mods and d != mod}
    return graph


def test_no_import_cycles() -> None:
    graph = _graph()
    done: set[str] = set()

    def visit(m: str, stack: list[str]) -> None:
        assert m not in stack, f"import cycle: {' -> '.join([*stack[stack.index(m) :], m])}"
        if m in done:
            return
        for d in sorted(graph[m]):
            visit(d, [*stack, m])
        done.add(m)

    for m in sorted(graph):
        visit(m, [])


def test_dependencies_point_one_way() -> None:
    graph = _graph()
    for mod, deps in graph.items():
        pkg = mod.split(".")[1]
        if pkg in ("stereo", "sim"):  # shared foundations know neither problem
            assert not [d for d in deps if d.startswith("traffictwin.risk")], mod
        if pkg == "stereo":
            assert not [d for d in deps if d.startswith("traffictwin.sim")], mod
    # the metric defines the risk <-> THW conversion: it depends on no other risk module
    assert not [d for d in graph["traffictwin.risk.metric"] if d.startswith("traffictwin.risk")]
    assert "traffictwin.risk.evaluation" not in graph["traffictwin.risk.baselines"]
