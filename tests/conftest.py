"""Test-session set-up.

torch and numba each load an OpenMP runtime whose idle threads spin; on two cores they spin
against each other's work (see ``plenoctree.runtime``). The CLI sets ``OMP_WAIT_POLICY=PASSIVE``
before either loads; tests import torch before calling the CLI in-process, so the policy is
set here, before either runtime is loaded (``./run test`` also exports it).

Triton's interpreter must be chosen before ``triton`` is first imported (its standard library
is built at import): on machines without CUDA the session sets ``TRITON_INTERPRET=1``. That
alone changes nothing else: Triton runs on CPU tensors only where ``PLENOCTREE_TRITON_CPU=1``
too, which ``tests/test_triton_kernels.py`` sets for its own tests.
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def _no_cuda() -> bool:
    import torch

    return not torch.cuda.is_available()


if _no_cuda():
    os.environ.setdefault("TRITON_INTERPRET", "1")


import pytest  # noqa: E402


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    """A 16x16 procedural Blender dataset (2 train, 1 val, 3 test views) and its 32^3 tree:
    ``root / "data"``, ``root / "tree.npz"``."""
    from plenoctree.datasets.procedural import procedural_tree, write_procedural_dataset
    from plenoctree.octree import save_tree

    root = tmp_path_factory.mktemp("scene")
    write_procedural_dataset(root / "data", n_train=2, n_val=1, n_test=3, width=16, height=16)
    save_tree(procedural_tree(32), root / "tree.npz", precision="fp32")
    return root


@pytest.fixture
def triton_cpu(monkeypatch):
    """Triton's GPU kernels on CPU tensors for one test (``PLENOCTREE_TRITON_CPU=1`` in the
    interpreter chosen above; with a CUDA device nothing changes); skipped without triton or
    without the interpreter."""
    pytest.importorskip("triton")
    if _no_cuda():
        if os.environ.get("TRITON_INTERPRET") != "1":
            pytest.skip("TRITON_INTERPRET=1 must be set before triton is imported (conftest.py)")
        monkeypatch.setenv("PLENOCTREE_TRITON_CPU", "1")
