"""The package root is lazy and the CLI sets its runtime up in-process (no re-exec)."""

from __future__ import annotations

import os
import subprocess
import sys

HEAVY = ("torch", "numba")


def _run(code: str, env: dict | None = None) -> str:
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True,
                         text=True, env=env)
    return out.stdout.strip()


def test_import_plenoctree_and_backend_policy_load_neither_torch_nor_numba():
    code = ("import sys, plenoctree, plenoctree.backend as b; b.resolve('render', 'auto'); "
            "import plenoctree.nerf, plenoctree.optim, plenoctree.convert, plenoctree.compression; "
            f"print([m for m in {HEAVY!r} if m in sys.modules])")
    assert _run(code) == "[]"


def test_help_builds_every_parser_without_torch_and_sets_the_runtime_in_process():
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    code = ("import sys, os, contextlib, io\n"
            "from plenoctree.cli import main\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n"
            "    try: main(['--help'])\n"
            "    except SystemExit: pass\n"
            "    for cmd in ('train', 'extract', 'finetune', 'run', 'eval', 'render'):\n"
            "        try: main([cmd, '--help'])\n"
            "        except SystemExit: pass\n"
            f"print([m for m in {HEAVY!r} if m in sys.modules])\n"
            "main(['info', '--json'])\n"
            "print('OMP', os.environ.get('OMP_WAIT_POLICY'))\n")
    out = _run(code, env).splitlines()
    assert out[0] == "[]", out
    assert out[-1] == "OMP PASSIVE"          # set by runtime.configure(), before torch loaded


def test_lazy_names_resolve_after_their_submodules_are_imported():
    import plenoctree
    import plenoctree.compression.codec  # noqa: F401  (the subpackage behind `compress`)
    import plenoctree.optim.finetuning  # noqa: F401

    for name in plenoctree.__all__:
        assert getattr(plenoctree, name) is not None, name
    assert callable(plenoctree.compress) and callable(plenoctree.finetune)
    assert callable(sys.modules["plenoctree.optim"].finetune)
    assert "train" in dir(plenoctree)
