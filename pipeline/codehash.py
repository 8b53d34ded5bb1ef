"""The code a node runs, as a hash: a stage module's in-repository import closure and kernels.

A node's cache key must change when any code it executes changes, and only then
(docs/software.md, "Cache keys").  The closure is read from the source, not
from what happens to be imported: every ``import`` / ``from ... import`` statement
of the stage module, function-local ones included, that names a module of the
``dermis`` package is followed, recursively.  Engine bookkeeping modules
(:data:`NOT_RESULTS`: the executor, the store, the planner, the scene checks and memory
estimates, the CLI) cannot change a stage's output and are neither hashed nor followed;
the scene schema (pipeline/config.py: its dataclasses and defaults, which stages rebuild
their config slices from) is hashed like any module a stage imports.  Every module in the
closure may declare ``KERNELS`` (``.cl`` file names it builds); those files and the
headers they ``#include`` are hashed too, and so are the files it declares in ``DATA_FILES``
(paths relative to its own folder: the HTML, CSS and JavaScript the report page inlines).
A node also hashes the modules it names in ``Node.code`` (the model a render node looks up
by name).

Probe: tests/test_structure.py (``PROBE``) appends a comment to files and checks that
exactly the nodes executing them get new keys.
"""
from __future__ import annotations

import ast
import functools
import hashlib
import importlib.util
from pathlib import Path

__all__ = ["module_closure", "closure_hash", "NOT_RESULTS", "read_source"]

ROOT_PACKAGE = "dermis"

# Modules whose code decides WHICH nodes run and WHERE results go, never WHAT a node computes.
NOT_RESULTS = frozenset({
    "dermis.pipeline.graph", "dermis.pipeline.store", "dermis.pipeline.api",
    "dermis.pipeline.cli", "dermis.pipeline.plan",
    "dermis.pipeline.errors", "dermis.pipeline.codehash", "dermis.pipeline.resources",
    "dermis.pipeline.scene_rules",
    "dermis.pipeline.registry", "dermis.pipeline", ROOT_PACKAGE,
})


def read_source(path: Path) -> bytes:
    """The bytes hashed for a source file (a seam for the key probe in the tests, which then
    call :func:`clear` since closures and hashes are memoised per process)."""
    return Path(path).read_bytes()


@functools.lru_cache(maxsize=None)
def _package_root() -> Path:
    spec = importlib.util.find_spec(ROOT_PACKAGE)
    return Path(list(spec.submodule_search_locations)[0])


@functools.lru_cache(maxsize=None)
def _module_file(name: str) -> Path | None:
    """The source file of an in-repository module, found on disk: nothing is imported (asking
    importlib would import every parent package, and for ``pkg.module.function`` the module)."""
    parts = name.split(".")
    if parts[0] != ROOT_PACKAGE or not all(p.isidentifier() for p in parts):
        return None
    here = _package_root()
    for part in parts[1:-1]:
        here = here / part
        if not (here / "__init__.py").is_file():
            return None
    if len(parts) == 1:
        return here / "__init__.py"
    for candidate in (here / parts[-1] / "__init__.py", here / f"{parts[-1]}.py"):
        if candidate.is_file():
            return candidate
    return None


def _is_module(name: str) -> bool:
    return _module_file(name) is not None


@functools.lru_cache(maxsize=None)
def _module_facts(name: str) -> tuple[frozenset, tuple, tuple]:
    """(the ``dermis.*`` modules imported anywhere in module ``name``, the ``KERNELS`` and
    the ``DATA_FILES`` it declares), from one parse of its source."""
    tree = ast.parse(read_source(_module_file(name)))
    return (frozenset(_imported_names(name, tree)), _declared(tree, "KERNELS"),
            _declared(tree, "DATA_FILES"))


def _imported_names(name: str, tree: ast.AST) -> set[str]:
    """Dotted ``dermis.*`` module names imported anywhere in ``tree`` (module ``name``)."""
    package = name if _module_file(name).name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            found.add(mod)
            # "from dermis.geometry import scan": the names may be submodules themselves
            found.update(f"{mod}.{a.name}" for a in node.names if _is_module(f"{mod}.{a.name}"))
    return {m for m in found if m == ROOT_PACKAGE or m.startswith(ROOT_PACKAGE + ".")}


@functools.lru_cache(maxsize=None)
def module_closure(name: str) -> tuple[str, ...]:
    """Sorted in-repository modules that ``name`` runs (itself included, bookkeeping excluded)."""
    seen: set[str] = set()
    todo = [name]
    while todo:
        mod = todo.pop()
        if mod in seen or (mod in NOT_RESULTS and mod != name) or not _is_module(mod):
            continue
        seen.add(mod)
        todo.extend(_module_facts(mod)[0])
    return tuple(sorted(seen))


def clear() -> None:
    """Forget memoised closures and hashes (after source files changed in this process)."""
    module_closure.cache_clear()
    closure_hash.cache_clear()
    _module_facts.cache_clear()


def _kernels_of(name: str) -> tuple[str, ...]:
    """The ``KERNELS`` a module declares, read statically (no import, no side effects)."""
    return _module_facts(name)[1]


def _declared(tree: ast.Module, what: str) -> tuple[str, ...]:
    for node in tree.body:
        targets = node.targets if isinstance(node, ast.Assign) else (
            [node.target] if isinstance(node, ast.AnnAssign) else [])
        if any(isinstance(t, ast.Name) and t.id == what for t in targets):
            return tuple(ast.literal_eval(node.value))
    return ()


@functools.lru_cache(maxsize=None)
def closure_hash(name: str) -> str:
    """sha256 over the source of every module in the closure and every kernel file they build."""
    from .cl import kernel_closure

    h = hashlib.sha256()
    kernels: set[str] = set()
    for mod in module_closure(name):
        h.update(mod.encode() + b"\0" + read_source(_module_file(mod)) + b"\0")
        kernels.update(_kernels_of(mod))
        for rel in _module_facts(mod)[2]:
            h.update(rel.encode() + b"\0" + read_source(_module_file(mod).parent / rel) + b"\0")
    for path in kernel_closure(sorted(kernels)):
        h.update(path.name.encode() + b"\0" + read_source(path) + b"\0")
    return h.hexdigest()
