"""The one backend policy (plenoctree.backend): names, devices, errors, registration."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from plenoctree import _triton, backend
from plenoctree.errors import BackendError

BUILTIN_OPS = ["composite", "finetune", "hashgrid", "march", "march_fixed", "mlp", "ray_batch",
               "render", "render_grad", "sh_colors", "terminate", "visibility"]
#: GPU-step ops without a numba kernel: on the CPU their torch twin runs
NO_NUMBA = {"mlp", "terminate"}
TRITON_OPS = {op for op, _ in _triton.TRITON_IMPLS}


def _triton_if_usable(op: str) -> list[str]:
    """``["triton"]`` where op ``op`` has a Triton kernel that can run in this process (CUDA
    with the triton package, or Triton's interpreter), else ``[]``: the registry lists it
    between numba and the torch twin, and ``auto`` takes it for CUDA tensors."""
    return ["triton"] if op in TRITON_OPS and _triton.usable_anywhere() else []


def test_every_op_has_numba_and_torch_and_auto_follows_the_device():
    assert backend.ops() == BUILTIN_OPS
    for op in BUILTIN_OPS:
        cpu = [] if op in NO_NUMBA else ["numba"]
        assert backend.backends(op) == [*cpu, *_triton_if_usable(op), "torch"]
        assert backend.resolve(op, "auto", "cpu") == (cpu or ["torch"])[0]
        on_cuda = [*_triton_if_usable(op), "torch"][0]
        assert backend.resolve(op, "AUTO", torch.device("cuda", 0)) == on_cuda
        assert backend.resolve(op, "torch", "cuda:1") == "torch"
        for name in (*cpu, "torch"):
            assert callable(backend.implementation(op, name)), (op, name)


def test_misspelled_or_wrong_device_names_raise_listing_what_is_available():
    listed = ", ".join(["auto", "numba", *_triton_if_usable("march"), "torch"])
    with pytest.raises(BackendError, match=rf"march: unknown backend 'nmuba'; available: "
                                           rf"{listed}$"):
        backend.resolve("march", "nmuba")
    on_cuda = ", ".join([*_triton_if_usable("render"), "torch"])
    with pytest.raises(BackendError, match=rf"backend 'numba' runs on cpu inputs, got cuda; "
                                           rf"available on cuda: {on_cuda}$"):
        backend.resolve("render", "numba", "cuda:0")
    with pytest.raises(BackendError, match="unknown op"):
        backend.resolve("nope", "auto")


def test_sh_colors_misspelled_backend_no_longer_falls_back_silently():
    from plenoctree.nerf.model import sh_colors

    c = torch.zeros(4, 3 * 4)
    d = torch.nn.functional.normalize(torch.randn(4, 3), dim=-1)
    torch.testing.assert_close(sh_colors(c, d, 1, "torch"), sh_colors(c, d, 1, "numba"))
    with pytest.raises(BackendError, match="sh_colors: unknown backend 'numab'"):
        sh_colors(c, d, 1, backend="numab")


def test_device_type_of_inputs():
    assert backend.device_type(np.zeros(3)) == "cpu"
    assert backend.device_type(None) == "cpu"
    assert backend.device_type(torch.zeros(1)) == "cpu"
    assert backend.device_type("cuda:3") == "cuda"
    assert backend.device_type(torch.device("cuda")) == "cuda"


def test_registered_kernel_wins_auto_on_its_device_and_is_called(monkeypatch):
    from plenoctree.render import render_rays
    from plenoctree.octree import Octree

    monkeypatch.setattr(backend, "_REGISTRY", {k: dict(v) for k, v in backend._REGISTRY.items()})
    monkeypatch.setattr(backend, "_LOADED", {})
    calls = []

    def fake(tree, info, origins, dirs, opts, device):
        calls.append(tuple(origins.shape))
        return backend.implementation("render", "torch")(tree, info, origins, dirs, opts, device)

    backend.register_backend("render", "fake", fake, devices=("cpu",), priority=99)
    backend.register_backend("render", "absent", fake, devices=("cpu",), priority=100,
                             available=lambda: False)
    assert backend.backends("render") == ["fake", "numba", "torch"]
    assert backend.resolve("render", "auto", "cpu") == "fake"
    with pytest.raises(BackendError, match="cannot run here"):
        backend.resolve("render", "absent")
    tree = Octree.dense(2, "SH1", center=[0, 0, 0], radius=1.0, seed=0)
    o = np.array([[0.0, 0.0, -3.0]], np.float32)
    d = np.array([[0.0, 0.0, 1.0]], np.float32)
    out = render_rays(tree, o, d)
    assert calls == [(1, 3)]
    torch.testing.assert_close(out.rgb, render_rays(tree, o, d, backend="numba").rgb)

