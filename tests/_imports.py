"""Imports of a Python file, as dotted names, read with ``ast`` (shared by the house-rule tests)."""

from __future__ import annotations

import ast


def imported_names(tree: ast.Module, package: str) -> set[str]:
    """Every name ``tree`` imports anywhere (module level or inside functions), absolute and
    dotted: ``import a.b`` gives ``a.b``; ``from a import b`` gives ``a`` and ``a.b`` (``b`` may be
    a module or an attribute). Relative imports are resolved against ``package``, the dotted
    package the file lives in."""
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            mod = node.module or ""
            if node.level:
                parts = package.split(".") if package else []
                mod = ".".join(parts[: len(parts) - node.level + 1] + ([mod] if mod else []))
            out.add(mod)
            out.update(f"{mod}.{a.name}" for a in node.names)
    return out
