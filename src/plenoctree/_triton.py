"""When the Triton GPU kernels can run, and the one place that decides it.

The GPU kernels (``render/_triton_impl.py``, ``optim/_triton_grad.py``,
``nerf/_hashgrid_triton.py``, ``nerf/_march_triton.py``) are written in Triton, which ships with
the CUDA builds of torch and compiles the kernels at first use (no build step, no CUDA toolkit).
They run

* on CUDA tensors when ``triton`` is importable and a CUDA device is present, and
* on CPU tensors through Triton's interpreter when the environment has ``TRITON_INTERPRET=1``
  (set before the kernel modules are first imported): the tests run every kernel this way
  against its torch twin on machines without a GPU. The interpreter is slow (NumPy per block):
  for tiny inputs only.

:func:`triton_usable` is the dispatch rule every ``backend="auto"`` follows: CUDA tensors go to
the Triton kernel when it is usable, otherwise to the torch twin; CPU tensors keep the numba
kernels. Moving this function into a shared backend policy changes no caller.
"""

from __future__ import annotations

import functools
import importlib.util
import os

import torch

from .errors import BackendError

__all__ = ["has_triton", "interpret_mode", "triton_usable", "require_triton"]


@functools.cache
def has_triton() -> bool:
    """True when the ``triton`` package is importable (CUDA builds of torch ship it)."""
    return importlib.util.find_spec("triton") is not None


def interpret_mode() -> bool:
    """True when ``TRITON_INTERPRET=1``: Triton kernels run on CPU tensors (tests only)."""
    return os.environ.get("TRITON_INTERPRET", "0").strip().lower() in ("1", "true", "yes", "on")


def triton_usable(device: torch.device | str) -> bool:
    """Whether a Triton kernel can run on tensors of ``device``.

    CUDA: ``triton`` importable and CUDA available. CPU: only in interpreter mode.
    """
    dev = torch.device(device)
    if not has_triton():
        return False
    if dev.type == "cuda":
        return torch.cuda.is_available()
    return dev.type == "cpu" and interpret_mode()


def require_triton(device: torch.device | str, what: str) -> None:
    """Raise :class:`BackendError` naming what is missing when Triton cannot run on ``device``."""
    if triton_usable(device):
        return
    dev = torch.device(device)
    if not has_triton():
        raise BackendError(f"{what}: backend 'triton' needs the triton package (shipped with "
                           "CUDA builds of torch; pip install triton)")
    if dev.type == "cpu":
        raise BackendError(f"{what}: backend 'triton' runs on CUDA tensors (or on CPU tensors "
                           "with TRITON_INTERPRET=1, for tests); got CPU tensors")
    raise BackendError(f"{what}: backend 'triton' cannot run on {dev} (CUDA not available)")
