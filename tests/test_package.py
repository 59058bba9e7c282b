"""Package-level checks: importing compiles nothing, the CLI's info and help run (the flat API
itself is pinned in ``test_public_api.py``)."""

import subprocess
import sys


def test_import_compiles_nothing():
    # Importing the package (and the CLI parser) must not JIT-compile numba kernels or import
    # the numba kernel modules.
    code = (
        "import sys, plenoctree, plenoctree.cli\n"
        "plenoctree.cli.build_parser()\n"
        "bad = [m for m in sys.modules if m.endswith('_numba') or '_numba_' in m "
        "or m.endswith('_numba_impl') or m.endswith('_render_grad')]\n"
        "assert not bad, bad\n"
        "import numba.core.registry as r\n"
        "print('ok')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "ok" in out.stdout


def test_cli_info_runs(capsys):
    from plenoctree.cli import main

    assert main(["info"]) == 0
    text = capsys.readouterr().out
    assert "torch" in text and "backends" in text


def test_cli_without_command_prints_help(capsys):
    from plenoctree.cli import main

    assert main([]) == 2
    assert "usage" in capsys.readouterr().out.lower()
