"""The layering of the package, as a test: which part of ``plenoctree`` may import which.

Every ``import`` in ``src/plenoctree`` is read with :mod:`ast` (module-level and deferred ones
inside functions alike: a deferred import is still a dependency) and checked against
:data:`ALLOWED`, the one table of allowed edges. A failure names the offending ``file:line``.

A *unit* is a top-level module (``video``, ``_util``) or a subpackage (``datasets``,
``render``); imports inside one unit are free. The layers, bottom up (DESIGN.md §1)::

    leaves     errors _bounds _log _lazy _npz _util runtime device _triton backend sh metrics plots
               live (a run's live.json) _sh_triton (the SH kernels for Triton)
    data       octree; datasets (octree/sh only for the procedural scenes, see EXCEPTIONS)
    engine     render (octree, sh); compression (octree)
    stages     evaluation camera_path export process viewer; nerf video compression_report;
               convert optim
    top        _config pipeline demo; cli (everything); nothing imports cli

The root package (``plenoctree/__init__.py``: lazy names over ``_lazy`` and ``errors``) may be
imported by any unit for ``__version__`` only.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
PKG = "plenoctree"

#: What every unit may import: the error types and the bounds policy of every setting.
_LEAF = {"errors", "_bounds"}
#: unit -> the units it may import (besides itself). The graph must stay acyclic.
ALLOWED: dict[str, set[str]] = {
    "errors": set(),
    "_bounds": {"errors"},
    "_log": set(),
    "_lazy": set(),
    "_npz": _LEAF,
    "_util": _LEAF | {"_npz"},
    "runtime": _LEAF,
    "device": _LEAF | {"runtime"},
    "_triton": _LEAF,
    "backend": _LEAF | {"_triton"},
    "sh": _LEAF,
    "metrics": _LEAF | {"_util"},
    "plots": _LEAF | {"_util"},
    "live": _LEAF | {"_util"},
    "_sh_triton": _LEAF | {"sh", "_triton"},
    "octree": _LEAF | {"_util", "_npz"},
    "datasets": _LEAF | {"_util"},
    "render": _LEAF | {"_util", "_triton", "backend", "octree", "sh", "_sh_triton"},
    "compression": _LEAF | {"_util", "_npz", "octree"},
    "evaluation": _LEAF | {"_util", "backend", "device", "metrics", "plots", "datasets",
                           "octree", "render", "compression"},
    "camera_path": _LEAF | {"_util", "datasets"},
    "export": _LEAF | {"_util", "octree", "render", "sh"},
    "process": _LEAF | {"_util", "datasets"},
    "viewer": _LEAF | {"_util", "_npz", "datasets", "compression", "render", "live"},
    "nerf": _LEAF | {"_lazy", "_util", "_triton", "backend", "runtime", "sh", "datasets",
                     "evaluation", "octree", "live", "_sh_triton"},
    "video": _LEAF | {"_util", "device", "plots", "datasets", "render", "compression",
                      "camera_path"},
    "compression_report": _LEAF | {"datasets", "octree", "render", "compression", "evaluation"},
    "convert": _LEAF | {"_lazy", "_util", "_triton", "backend", "device", "runtime", "sh",
                        "datasets", "octree", "render", "evaluation", "nerf"},
    "optim": _LEAF | {"_lazy", "_util", "_triton", "backend", "device", "plots", "datasets",
                      "octree", "render", "evaluation", "sh"},
    "_config": _LEAF,
    "pipeline_config": _LEAF | {"_config", "compression", "convert", "nerf", "optim",
                                "process"},
    "pipeline_summary": _LEAF | {"_config", "device"},
    "pipeline_budget": _LEAF | {"_util", "datasets", "optim", "pipeline_config"},
    "pipeline": _LEAF | {"_config", "_util", "device", "plots", "datasets", "octree", "live",
                         "compression", "evaluation", "process", "nerf", "convert", "optim",
                         "video", "viewer", "pipeline_config", "pipeline_summary",
                         "pipeline_budget"},
    "demo": _LEAF | {"_util", "datasets", "optim", "convert", "pipeline", "pipeline_config",
             "nerf"},
    "cli": None,          # everything (filled in below)
    "__main__": {"cli"},
}

#: Deliberate exceptions, one edge of one module each: (importing module, imported unit) ->
#: why. An entry that no import uses any more fails the test (delete it).
EXCEPTIONS: dict[tuple[str, str], str] = {
    ("plenoctree.datasets.procedural", "sh"):
        "the procedural scene's colours are SH coefficients (the scene the tests render)",
    ("plenoctree.datasets.procedural", "octree"):
        "procedural_tree() builds the scene's Octree for tests and the demo (deferred import)",
    ("plenoctree.datasets.forward_facing", "sh"):
        "the forward-facing procedural scene, as procedural",
    ("plenoctree.datasets.forward_facing", "octree"):
        "forward_facing_tree() builds its NDC Octree for tests (deferred import)",
    ("plenoctree._config", "nerf"):
        "_config.field_docs reads nerf.config's field docstrings; to move into _config "
        "(code review 2026-12 §2.6.4) with the pipeline configs",
}

ALLOWED["cli"] = set(ALLOWED) - {"cli", "__main__"}
#: What the root ``__init__`` itself imports (its flat names are lazy: :mod:`plenoctree._lazy`).
ROOT_ALLOWED = {"_lazy", "errors"}


def _modules() -> dict[str, Path]:
    out = {}
    for path in sorted((SRC / PKG).rglob("*.py")):
        parts = list(path.relative_to(SRC).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = path
    return out


MODULES = _modules()


def _is_package(mod: str) -> bool:
    return MODULES[mod].name == "__init__.py"


def _unit(mod: str) -> str:
    parts = mod.split(".")
    return parts[1] if len(parts) > 1 else PKG


def _target(mod: str, node: ast.ImportFrom | ast.Import) -> list[tuple[str, list[str]]]:
    """``(imported module, names taken from it)`` for one import statement of ``mod``."""
    if isinstance(node, ast.Import):
        return [(a.name, []) for a in node.names]
    if node.level:
        base = mod.split(".")
        if not _is_package(mod):
            base = base[:-1]
        base = base[:len(base) - (node.level - 1)]
        prefix = ".".join(base + ([node.module] if node.module else []))
    else:
        prefix = node.module or ""
    out = []
    for a in node.names:          # `from pkg import submodule` imports the submodule
        sub = f"{prefix}.{a.name}"
        out.append((sub, []) if sub in MODULES else (prefix, [a.name]))
    return out


def _imports() -> list[tuple[str, int, str, list[str]]]:
    """``(module, line, imported plenoctree module, names)`` for every import in ``src/``."""
    found = []
    for mod, path in MODULES.items():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                for target, names in _target(mod, node):
                    if target == PKG or target.startswith(PKG + "."):
                        found.append((mod, node.lineno, target, names))
    return found


IMPORTS = _imports()


def _where(mod: str, line: int) -> str:
    return f"{MODULES[mod].relative_to(SRC.parent)}:{line}"


def test_every_unit_is_in_the_table():
    units = {_unit(m) for m in MODULES} - {PKG}
    assert units == set(ALLOWED), (f"not in ALLOWED: {sorted(units - set(ALLOWED))}; "
                                   f"no longer exist: {sorted(set(ALLOWED) - units)}")


def test_the_table_is_acyclic():
    state: dict[str, int] = {}

    def visit(u: str, path: list[str]) -> None:
        if state.get(u) == 2:
            return
        assert state.get(u) != 1, f"ALLOWED has a cycle: {' -> '.join(path + [u])}"
        state[u] = 1
        for v in sorted(ALLOWED[u]):
            visit(v, path + [u])
        state[u] = 2

    for u in sorted(ALLOWED):
        visit(u, [])


def test_imports_follow_the_layers():
    bad, used = [], set()
    for mod, line, target, names in IMPORTS:
        src, dst = _unit(mod), _unit(target)
        if dst == src:
            continue
        if dst == PKG:
            if names != ["__version__"]:
                bad.append(f"{_where(mod, line)}: imports {names or target} from the root "
                           "package (only __version__ may be; import from the submodule)")
            continue
        if dst in (ROOT_ALLOWED if src == PKG else ALLOWED[src]):
            continue
        if (mod, dst) in EXCEPTIONS:
            used.add((mod, dst))
            continue
        bad.append(f"{_where(mod, line)}: {src} may not import {dst} ({target})")
    assert not bad, "layer violations:\n" + "\n".join(bad)
    stale = set(EXCEPTIONS) - used
    assert not stale, f"EXCEPTIONS no import needs any more (delete them): {sorted(stale)}"


def test_nothing_but_the_entry_points_imports_cli():
    bad = [f"{_where(m, line)}: imports {t}" for m, line, t, _ in IMPORTS
           if _unit(t) == "cli" and _unit(m) not in ("cli", "__main__")]
    assert not bad, "\n".join(bad)


def _bound_names(package: str) -> set[str]:
    """Names a package ``__init__`` binds: definitions, assignments, imports, and the keys of
    its lazy table (``_LAZY = {"name": ".module", ...}``)."""
    tree = ast.parse(MODULES[package].read_text(encoding="utf-8"))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            names.add(node.id)
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            names.update((a.asname or a.name).split(".")[0] for a in node.names)
        elif isinstance(node, ast.Assign) and any(
                isinstance(t, ast.Name) and t.id == "_LAZY" for t in node.targets):
            names.update(k.value for k in getattr(node.value, "keys", [])
                         if isinstance(k, ast.Constant))
    return names


def test_every_import_names_an_existing_module():
    """A deferred import of a module or package attribute that does not exist fails only when
    its function runs: catch it here."""
    bad = []
    for mod, line, target, names in IMPORTS:
        if target not in MODULES:
            bad.append(f"{_where(mod, line)}: no module {target}")
        elif names and _is_package(target):
            bound = _bound_names(target)
            bad += [f"{_where(mod, line)}: {target} has no {n!r}" for n in names
                    if n != "*" and n not in bound]
    assert not bad, "\n".join(bad)


#: Module-level import cycles (deferred imports counted) that are deliberate.
CYCLE_EXCEPTIONS = {
    frozenset({"plenoctree.octree.tree", "plenoctree.octree.build", "plenoctree.octree.check"}):
        "the svox-style facade: Octree.from_grid / dense / check_integrity defer to build and "
        "check, which import Octree and parse_data_format from tree (code review 2026-12 "
        "§2.6.3: a future octree/format.py removes it)",
}


def _cycles() -> list[frozenset[str]]:
    """Strongly connected components (> 1 module) of the module import graph. An import of a
    package from inside it (``from .. import backend`` excepted: that names a module) is
    left out: importing a submodule runs its parents' ``__init__`` anyway."""
    graph: dict[str, set[str]] = {m: set() for m in MODULES}
    for mod, _, target, _ in IMPORTS:
        if target in MODULES and target != mod and not (
                _is_package(target) and mod.startswith(target + ".")):
            graph[mod].add(target)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[frozenset[str]] = []

    def strong(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = set()
            while True:
                w = stack.pop()
                on.discard(w)
                comp.add(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(frozenset(comp))

    for v in sorted(graph):
        if v not in index:
            strong(v)
    return out


def test_no_import_cycles_between_modules():
    cycles = _cycles()
    bad = [sorted(c) for c in cycles if c not in CYCLE_EXCEPTIONS]
    assert not bad, f"import cycles (deferred imports included): {bad}"
    stale = set(CYCLE_EXCEPTIONS) - set(cycles)
    assert not stale, f"CYCLE_EXCEPTIONS that no longer exist (delete them): {stale}"


@pytest.mark.parametrize("edge", sorted(EXCEPTIONS))
def test_each_exception_has_a_reason(edge):
    assert len(EXCEPTIONS[edge]) > 20
