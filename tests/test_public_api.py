"""The public surface, pinned: ``plenoctree.__all__`` name by name with its kind, every name
resolving, and no name of any package hiding one of its modules.

A change to the flat API must change :data:`API` here (and say so in the changelog). The
trap this guards against: a package that exports a function under the name of one of its own
submodules (``plenoctree.compress`` the function vs a ``plenoctree/compress/`` package) makes
``import plenoctree.compress as c`` give the function or the module depending on import order.
"""

from __future__ import annotations

import importlib
import inspect
import pkgutil
import subprocess
import sys
import types

import pytest

import plenoctree

#: Every name of ``plenoctree.__all__`` -> its kind ("class", "function" or "str").
API: dict[str, str] = {
    "__version__": "str",
    # errors
    "PlenOctreeError": "class", "DatasetError": "class", "TreeFormatError": "class",
    "BackendError": "class", "ConfigError": "class",
    # sh
    "eval_sh_bases": "function", "eval_sg_bases": "function", "num_sh_bases": "function",
    "sh_degree_from_bases": "function",
    # datasets
    "Cameras": "class", "Dataset": "class", "generate_rays": "function",
    "load_blender": "function", "load_dataset": "function",
    "write_procedural_dataset": "function", "procedural_grid": "function",
    "procedural_tree": "function",
    # metrics
    "psnr": "function", "ssim": "function", "lpips": "function", "lpips_available": "function",
    # octree
    "Octree": "class", "save_tree": "function", "load_tree": "function",
    "export_svox": "function", "import_svox": "function",
    # render
    "RenderOptions": "class", "RenderOutput": "class", "render_rays": "function",
    "render_image": "function", "available_backends": "function",
    # the stages
    "TrainConfig": "class", "train": "function", "load_nerf": "function",
    "ExtractConfig": "class", "extract": "function",
    "FinetuneConfig": "class", "finetune": "function",
    "CompressOptions": "class", "compress": "function", "decompress": "function",
    "save_compressed": "function", "load_compressed": "function", "load_any_tree": "function",
    "EvalConfig": "class", "evaluate_tree": "function", "eval_tree_file": "function",
    "export_web": "function",
    "PipelineConfig": "class", "run_pipeline": "function",
}


def _kind(value: object) -> str:
    if inspect.isclass(value):
        return "class"
    if isinstance(value, types.ModuleType):
        return "module"
    return "function" if callable(value) else type(value).__name__


def _modules() -> list[str]:
    """Every module and package of plenoctree (``__main__`` entry points left out)."""
    return ["plenoctree"] + sorted(
        m.name for m in pkgutil.walk_packages(plenoctree.__path__, "plenoctree.")
        if not m.name.endswith(".__main__"))


def _packages() -> list[str]:
    return ["plenoctree"] + sorted(
        m.name for m in pkgutil.walk_packages(plenoctree.__path__, "plenoctree.") if m.ispkg)


def test_all_is_pinned():
    assert len(plenoctree.__all__) == len(set(plenoctree.__all__)), "duplicates in __all__"
    assert set(plenoctree.__all__) == set(API), (
        f"added: {sorted(set(plenoctree.__all__) - set(API))}, "
        f"removed: {sorted(set(API) - set(plenoctree.__all__))}")


@pytest.mark.parametrize("name", sorted(API))
def test_every_name_resolves_to_its_kind(name):
    value = getattr(plenoctree, name)
    assert value is not None
    assert _kind(value) == API[name], f"plenoctree.{name} is a {_kind(value)}"


def test_dir_lists_the_lazy_names():
    assert set(API) <= set(dir(plenoctree))


@pytest.mark.parametrize("package", _packages())
def test_no_exported_name_is_a_submodule_name(package):
    pkg = importlib.import_module(package)
    subs = {m.name for m in pkgutil.iter_modules(pkg.__path__)}
    exported = set(getattr(pkg, "__all__", ())) | set(getattr(pkg, "_LAZY", {}))
    assert not exported & subs, (
        f"{package} exports {sorted(exported & subs)}, also the names of its submodules: "
        "rename the module (the exported name is the public API)")
    for name in subs & set(vars(pkg)):
        value = vars(pkg)[name]
        assert isinstance(value, types.ModuleType) and value.__name__ == f"{package}.{name}", (
            f"{package}.{name} is a {_kind(value)}, hiding the module {package}.{name}")


def test_every_module_imports_as_itself():
    """In a fresh process (import order matters to the trap): each module imported by name,
    then with ``import a.b as m``, then again after the flat API resolved every name."""
    code = (
        "import importlib, sys, types\n"
        "import plenoctree\n"
        f"names = {_modules()!r}\n"
        "bad = []\n"
        "def check(when):\n"
        "    for n in names:\n"
        "        if not isinstance(importlib.import_module(n), types.ModuleType):\n"
        "            bad.append((when, n, 'import_module'))\n"
        "        ns = {}\n"
        "        exec(f'import {n} as m', ns)\n"
        "        if ns['m'] is not sys.modules[n]:\n"
        "            bad.append((when, n, type(ns['m']).__name__))\n"
        "check('first')\n"
        "[getattr(plenoctree, a) for a in plenoctree.__all__]\n"
        "check('after the flat API resolved')\n"
        "print(bad)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.strip().splitlines()[-1] == "[]", out.stdout[-3000:]
