"""Each DVC stage's code deps, computed from the imports of its script (``manifests`` is the
``stage_code`` stage's command; the other actions are developer tools).

A stage re-runs when a file it imports changes, and only then. The import closure of a stage's
``python -m`` module is every file of ``pipelines/`` and ``src/traffictwin/`` it imports
(imports anywhere in a file, module level or inside functions, read with ``ast``) and the Jinja
templates those modules render. It is recorded once per script, in that script's *code manifest*
``stage_code/<script>.md5`` (``md5sum`` lines: the MD5 and path of every file of the closure,
script first; ``md5sum -c stage_code/train_fusion.md5`` checks them). The ``stage_code`` stage
writes the manifests; its deps are the two code folders (:data:`CODE_FOLDERS`, their
``__pycache__`` left out by ``.dvcignore``), so it re-runs (in a fraction of a second) after any
code edit. Every other stage depends on its script's manifest, which changes exactly when a file
of its closure does: dvc.lock records two folder hashes instead of each code file's hash once per
stage that imports it (DVC re-reads and rewrites the whole lock after every stage, so its length is
paid per stage). Data, model and config deps (any other path) are kept as written.

    python -m pipelines.stage_deps check        # exit 1 and list the stages whose deps differ
    python -m pipelines.stage_deps write        # rewrite the code deps (and manifest outs) of dvc.yaml
    python -m pipelines.stage_deps manifests    # write stage_code/*.md5 (the stage_code stage)
    python -m pipelines.stage_deps prune-lock   # drop dvc.lock entries of stages dvc.yaml no longer has

After editing code, ``dvc repro stage_code`` and then ``dvc status`` lists the stages the edit
re-runs. ``make run`` prunes the lock after ``dvc repro``; tests/test_dvc_deps.py runs the check.
"""

from __future__ import annotations

import argparse
import ast
import hashlib
import io
import re
import sys
from collections.abc import Iterable, Mapping
from functools import cache
from pathlib import Path
from typing import Any

from ruamel.yaml import YAML
from ruamel.yaml.comments import CommentedMap, CommentedSeq

from pipelines._paths import DVC_YAML, ROOT

SRC = ROOT / "src"
DVC_LOCK = ROOT / "dvc.lock"
CODE_ROOTS = ("src", "pipelines")
#: the folder of the code manifests and the stage that writes them
MANIFESTS = CODE_STAGE = "stage_code"
#: the module the ``stage_code`` stage runs
CODE_STAGE_MODULE = "pipelines.stage_deps"
#: the ``stage_code`` stage's code deps: the folders that hold every file of every closure
CODE_FOLDERS = ("pipelines", "src/traffictwin")


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


def module_file(mod: str, root: Path = ROOT) -> Path | None:
    """The file of module ``mod`` (``traffictwin.*`` under ``src/``, ``pipelines.*`` at the root)."""
    base = (root / "src" if mod.startswith("traffictwin") else root) / mod.replace(".", "/")
    for p in (base.with_suffix(".py"), base / "__init__.py"):
        if p.is_file():
            return p
    return None


def _stamp(path: Path) -> tuple[int, int]:
    st = path.stat()
    return st.st_mtime_ns, st.st_size


@cache
def _parsed(path: Path, stamp: tuple[int, int]) -> ast.Module:
    """``path`` parsed once per version (``stamp``: mtime, size): every stage's closure reads the
    same shared modules."""
    return ast.parse(path.read_text())


def _tree(path: Path) -> ast.Module:
    return _parsed(path, _stamp(path))


@cache
def _imports_of(path: Path, root: Path, stamp: tuple[int, int]) -> frozenset[str]:
    src = root / "src"
    rel = path.relative_to(src if src in path.parents else root).with_suffix("")
    package = ".".join(rel.parts[:-1])
    return frozenset(
        n
        for n in imported_names(_parsed(path, stamp), package)
        if n.split(".")[0] in ("traffictwin", "pipelines") and module_file(n, root)
    )


def _imports(path: Path, root: Path) -> set[str]:
    """Modules of traffictwin / pipelines that ``path`` imports (anywhere in the file)."""
    return set(_imports_of(path, root, _stamp(path)))


def _only_docs(f: Path) -> bool:
    """A package ``__init__`` with nothing but a docstring and ``__version__`` runs no stage code."""
    if f.name != "__init__.py":
        return False
    body = _tree(f).body
    return all(
        (isinstance(n, ast.Expr) and isinstance(n.value, ast.Constant))
        or (
            isinstance(n, ast.Assign)
            and [getattr(t, "id", "") for t in n.targets] == ["__version__"]
        )
        for n in body
    )


@cache
def closure(module: str, root: Path = ROOT) -> frozenset[Path]:
    """Files of every traffictwin/pipelines module ``module`` needs, transitively (package
    ``__init__`` files that hold only a docstring are left out: they run no stage code), and the
    Jinja templates those modules render (:func:`_templates`)."""
    seen: set[str] = set()
    todo = [module]
    while todo:
        m = todo.pop()
        if m in seen:
            continue
        seen.add(m)
        f = module_file(m, root)
        if f is not None:
            todo += sorted(_imports(f, root) - seen)
            parts = m.split(".")  # importing a.b.c runs a/__init__ and a/b/__init__ too
            todo += [".".join(parts[:i]) for i in range(1, len(parts))]
    files = {f for f in (module_file(m, root) for m in seen) if f is not None and not _only_docs(f)}
    return frozenset(files | {t for f in files for t in _templates(f)})


def _templates(module: Path) -> list[Path]:
    """The Jinja templates a module renders: every ``templates/*.j2`` beside it when its source
    names a ``.j2`` file (a string literal), else none. Templates are code: editing one changes
    what the stage writes."""
    folder = module.parent / "templates"
    if not folder.is_dir() or not _names_a_template(module, _stamp(module)):
        return []
    return sorted(folder.glob("*.j2"))


@cache
def _names_a_template(module: Path, stamp: tuple[int, int]) -> bool:
    """Whether ``module`` (at version ``stamp``) holds a string literal ending in ``.j2``; read
    once per version, as every stage's closure asks about the shared modules."""
    return any(
        isinstance(n, ast.Constant) and isinstance(n.value, str) and n.value.endswith(".j2")
        for n in ast.walk(_parsed(module, stamp))
    )


def is_code(dep: str) -> bool:
    """Whether a dvc.yaml dep is code (a path under ``src/`` or ``pipelines/``)."""
    return dep.split("/")[0] in CODE_ROOTS


def dep_path(dep: str | Mapping[str, Any]) -> str:
    """The path of a dvc.yaml dep entry (a string, or a one-key mapping with options)."""
    return dep if isinstance(dep, str) else next(iter(dep))


def stage_module(stage: Mapping[str, Any]) -> str:
    """The ``python -m`` module a stage's ``cmd`` runs."""
    return str(stage["cmd"]).split("python -m ")[1].split()[0]


def code_deps(module: str, root: Path = ROOT) -> list[str]:
    """The code deps of a stage running ``module``: its script first, then every other file of
    the import closure, sorted (``pipelines/`` before ``src/``)."""
    script = module_file(module, root)
    files = sorted(p.relative_to(root).as_posix() for p in closure(module, root) if p != script)
    return ([script.relative_to(root).as_posix()] if script else []) + files


def manifest_path(module: str) -> str:
    """The code manifest of the stages that run ``module``, relative to the repository root
    (``pipelines.train_fusion`` -> ``stage_code/train_fusion.md5``)."""
    return f"{MANIFESTS}/{module.rsplit('.', 1)[-1]}.md5"


def is_manifest(dep: str) -> bool:
    """Whether a dvc.yaml dep is a code manifest (:func:`manifest_path`)."""
    return dep.startswith(f"{MANIFESTS}/")


def manifest_text(module: str, root: Path = ROOT) -> str:
    """``md5sum`` lines (``<md5>  <path>``, paths relative to ``root``) of every file of
    :func:`code_deps` of ``module``, in that order: what a stage running ``module`` depends on."""
    return "".join(
        f"{hashlib.md5((root / p).read_bytes(), usedforsecurity=False).hexdigest()}  {p}\n"
        for p in code_deps(module, root)
    )


def stage_modules(doc: Mapping[str, Any]) -> list[str]:
    """The ``python -m`` modules of dvc.yaml's stages (``doc``), each once, sorted; the
    ``stage_code`` stage's own module left out."""
    bodies = _stage_bodies(doc).values()
    return sorted({stage_module(b) for b in bodies} - {CODE_STAGE_MODULE})


def wanted_deps(stage: Mapping[str, Any]) -> list[str]:
    """A stage's deps as they should read: its script's code manifest (the ``stage_code`` stage:
    the code folders, :data:`CODE_FOLDERS`), then its other deps."""
    others = [
        d
        for d in stage.get("deps", [])
        if not is_code(dep_path(d)) and not is_manifest(dep_path(d))
    ]
    module = stage_module(stage)
    if module == CODE_STAGE_MODULE:
        return [*CODE_FOLDERS, *others]
    return [manifest_path(module)] + others


def wanted_outs(modules: Iterable[str]) -> list[str]:
    """The ``stage_code`` stage's outs: one code manifest per stage module."""
    return [manifest_path(m) for m in modules]


def write_manifests(dvc_yaml: Path = DVC_YAML, root: Path | None = None) -> list[str]:
    """Write the code manifest of every stage module of ``dvc_yaml`` that differs from what the
    code gives (atomically; an unchanged one is left as it is) and remove manifests of modules no
    stage runs; returns the paths written or removed."""
    from traffictwin.io.atomic import write_text_atomic

    _, doc = _load(dvc_yaml)
    root = root or dvc_yaml.resolve().parent
    modules = stage_modules(doc)
    changed: list[str] = []
    for m in modules:
        path = root / manifest_path(m)
        text = manifest_text(m, root)
        if not path.is_file() or path.read_text() != text:
            write_text_atomic(path, text)
            changed.append(manifest_path(m))
    wanted = {root / p for p in wanted_outs(modules)}
    for stale in sorted((root / MANIFESTS).glob("*.md5")):
        if stale not in wanted:
            stale.unlink()
            changed.append(stale.relative_to(root).as_posix())
    return changed


def _load(path: Path) -> tuple[YAML, Any]:
    yaml = YAML()  # round trip: comments, anchors and flow style are kept
    yaml.width = 118
    yaml.indent(mapping=2, sequence=4, offset=2)
    yaml.preserve_quotes = True
    return yaml, yaml.load(path.read_text())


def _stage_bodies(doc: Mapping[str, Any]) -> dict[str, Any]:
    """dvc.yaml's stages by name (a ``foreach`` stage by its template's name: its ``do`` body)."""
    return {name: (s["do"] if "do" in s else s) for name, s in doc["stages"].items()}


def differences(dvc_yaml: Path = DVC_YAML) -> dict[str, tuple[list[str], list[str]]]:
    """Stages whose deps (the ``stage_code`` stage: deps and outs) are not as they should read
    (:func:`wanted_deps`, :func:`wanted_outs`): name -> (missing, stale)."""
    _, doc = _load(dvc_yaml)
    modules = stage_modules(doc)
    out: dict[str, tuple[list[str], list[str]]] = {}
    for name, body in _stage_bodies(doc).items():
        have = [dep_path(d) for d in body.get("deps", [])]
        want = wanted_deps(body)
        if stage_module(body) == CODE_STAGE_MODULE:
            have += [dep_path(o) for o in body.get("outs", [])]
            want += wanted_outs(modules)
        missing = [d for d in want if d not in have]
        stale = [d for d in have if d not in want]
        if missing or stale:
            out[name] = (missing, stale)
    return out


def write(dvc_yaml: Path = DVC_YAML) -> list[str]:
    """Rewrite the code deps of every stage in ``dvc_yaml`` (and the ``stage_code`` stage's
    outs); returns the names of the stages changed.

    The file is replaced atomically; a stage's non-code deps keep their order after the code."""
    yaml, doc = _load(dvc_yaml)
    modules = stage_modules(doc)
    changed: list[str] = []
    done: set[int] = set()  # a YAML anchor shared by two stages is one list: rewrite it once
    for name, body in _stage_bodies(doc).items():
        deps = body.get("deps")
        if stage_module(body) == CODE_STAGE_MODULE:
            outs = [{p: _flow({"cache": False})} for p in wanted_outs(modules)]
            if [dep_path(o) for o in body.get("outs", [])] != wanted_outs(modules):
                body["outs"] = _block(body.get("outs"), outs)
                changed.append(name)
        if deps is None or id(deps) in done:
            continue
        done.add(id(deps))
        want = wanted_deps(body)
        if [dep_path(d) for d in deps] == want:
            continue
        keep = {dep_path(d): d for d in deps if not is_code(dep_path(d))}
        body["deps"] = _block(deps, [keep.get(d, d) for d in want])
        if name not in changed:
            changed.append(name)
    if changed:
        buf = io.StringIO()
        yaml.dump(doc, buf)
        text = re.sub(
            r"[ \t]+$", "", buf.getvalue(), flags=re.MULTILINE
        )  # ruamel's flow-list breaks
        tmp = dvc_yaml.with_name(f".{dvc_yaml.name}.tmp")
        tmp.write_text(text)
        tmp.replace(dvc_yaml)
    return changed


def _flow(mapping: dict[str, Any]) -> CommentedMap:
    """``mapping`` written in flow style (``{cache: false}``)."""
    out = CommentedMap(mapping)
    out.fa.set_flow_style()
    return out


def _block(seq: Any, items: list[Any]) -> Any:
    """``items`` in place of the YAML sequence ``seq`` (kept, with its anchor, when it is one),
    in block style."""
    if isinstance(seq, CommentedSeq):
        seq[:] = items
        seq.fa.set_block_style()
        return seq
    return items


def expanded_stage_names(doc: Mapping[str, Any], params: Mapping[str, Any]) -> set[str]:
    """Names of every stage dvc.yaml defines, ``foreach`` stages expanded as DVC names them
    (``name@key`` for a mapping, ``name@item`` for a list), the foreach values from ``params``."""
    names: set[str] = set()
    for name, s in doc["stages"].items():
        if "foreach" not in s:
            names.add(name)
            continue
        ref = str(s["foreach"])
        if ref.startswith("${") and ref.endswith("}"):
            value: Any = params
            for key in ref[2:-1].split("."):
                value = value[key]
        else:
            value = s["foreach"]
        keys: Iterable[Any] = value.keys() if isinstance(value, Mapping) else value
        names.update(f"{name}@{k}" for k in keys)
    return names


def stale_lock_stages(dvc_yaml: Path = DVC_YAML, dvc_lock: Path = DVC_LOCK) -> list[str]:
    """Stages dvc.lock records that dvc.yaml (with params.yaml's foreach values) no longer has."""
    _, doc = _load(dvc_yaml)
    _, params = _load(dvc_yaml.with_name("params.yaml"))
    _, lock = _load(dvc_lock)
    current = expanded_stage_names(doc, params)
    return sorted(n for n in (lock.get("stages") or {}) if n not in current)


def prune_lock(dvc_yaml: Path = DVC_YAML, dvc_lock: Path = DVC_LOCK) -> list[str]:
    """Remove the stale stages from ``dvc_lock`` (atomic replace); returns their names."""
    stale = stale_lock_stages(dvc_yaml, dvc_lock)
    if stale:
        yaml, lock = _load(dvc_lock)
        yaml.width = 4096  # DVC writes the lock: keep its lines and indentation as they are
        yaml.indent(mapping=2, sequence=2, offset=0)
        for n in stale:
            del lock["stages"][n]
        tmp = dvc_lock.with_name(f".{dvc_lock.name}.tmp")
        with tmp.open("w") as f:
            yaml.dump(lock, f)
        tmp.replace(dvc_lock)
    return stale


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipelines.stage_deps", description=__doc__)
    parser.add_argument("action", choices=["check", "write", "manifests", "prune-lock"])
    args = parser.parse_args(argv)
    if args.action == "check":
        diff = differences()
        for name, (missing, stale) in diff.items():
            print(f"dvc.yaml stage {name}: missing {missing}, stale {stale}", file=sys.stderr)
        if diff:
            print("run `python -m pipelines.stage_deps write`", file=sys.stderr)
        return 1 if diff else 0
    if args.action == "write":
        changed = write()
        print(f"dvc.yaml: code deps rewritten for {len(changed)} stage(s) {changed}")
        return 0
    if args.action == "manifests":
        changed = write_manifests()
        print(f"{MANIFESTS}: {len(changed)} code manifest(s) written or removed {changed}")
        return 0
    pruned = prune_lock()
    print(f"dvc.lock: {len(pruned)} stale stage(s) removed {pruned}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
