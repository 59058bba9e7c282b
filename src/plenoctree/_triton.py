"""When the Triton GPU kernels can run, and the one place that decides it.

The GPU kernels (``render/_triton_impl.py``, ``optim/_triton_grad.py``,
``nerf/_hashgrid_triton.py``, ``nerf/_march_triton.py``, ``convert/_visibility_triton.py``)
are written in Triton, which ships with the CUDA builds of torch and compiles the kernels at
first use (no build step, no CUDA toolkit).
They run

* on CUDA tensors when ``triton`` is importable and a CUDA device is present, and
* on CPU tensors through Triton's interpreter when the environment has both
  ``TRITON_INTERPRET=1`` (read by Triton when it is first imported) and
  ``PLENOCTREE_TRITON_CPU=1`` (read at each call: the opt-in): the tests run every kernel this
  way against its torch twin on machines without a GPU. The interpreter is slow (NumPy per
  block): for tiny inputs only.

:mod:`plenoctree.backend` registers backend ``"triton"`` for the ops listed in
:data:`TRITON_IMPLS` (``render``, ``render_grad``, ``finetune``, ``hashgrid``, ``march``,
``march_fixed``, ``sh_colors``, ``composite``, ``ray_batch``, ``mlp``, ``terminate``,
``visibility``) with
:data:`TRITON_PRIORITY`, between numba (CPU) and the torch twin, and :func:`usable_anywhere` as
its availability probe: ``backend="auto"`` then picks Triton for CUDA tensors when it is usable
and keeps numba for CPU tensors; CPU tensors reach Triton only when asked for by name (in
interpreter mode). This module imports nothing of the package but :mod:`plenoctree.errors`
(``backend.py`` imports it, never the reverse) and imports torch lazily.
"""

from __future__ import annotations

import functools
import importlib.util
import os
import sys
from typing import Any

from .errors import BackendError

__all__ = ["has_triton", "interpret_mode", "triton_usable", "require_triton", "usable_anywhere",
           "TRITON_PRIORITY", "TRITON_IMPLS"]

#: Between the torch twin (0) and numba (10): first on CUDA, never ``auto``'s pick on the CPU.
TRITON_PRIORITY = 5

#: ``(op, "module:attr")`` of each Triton kernel; registered by :mod:`plenoctree.backend`.
TRITON_IMPLS = (
    ("render", "plenoctree.render._triton_impl:render_backend"),
    ("render_grad", "plenoctree.optim._triton_grad:render_grad_backend"),
    ("finetune", "plenoctree.optim._steppers:TritonStepper"),
    ("hashgrid", "plenoctree.nerf._hashgrid_triton:hashgrid_backend"),
    ("march", "plenoctree.nerf._march_triton:march_backend"),
    ("march_fixed", "plenoctree.nerf._march_triton:march_fixed_backend"),
    ("sh_colors", "plenoctree._sh_triton:sh_colors_backend"),
    ("composite", "plenoctree.nerf.composite:_composite_triton"),
    ("ray_batch", "plenoctree.nerf._raygen_triton:ray_batch_backend"),
    ("mlp", "plenoctree.nerf._mlp_triton:mlp_backend"),
    ("terminate", "plenoctree.nerf._terminate_triton:terminate_backend"),
    ("visibility", "plenoctree.convert.visibility:_max_weights_triton_run"),
)


@functools.cache
def has_triton() -> bool:
    """True when the ``triton`` package is importable (CUDA builds of torch ship it)."""
    return importlib.util.find_spec("triton") is not None


def _env_on(name: str) -> bool:
    return os.environ.get(name, "0").strip().lower() in ("1", "true", "yes", "on")


def interpret_mode() -> bool:
    """True when Triton kernels run on CPU tensors in Triton's interpreter (tests only):
    ``TRITON_INTERPRET=1`` and ``PLENOCTREE_TRITON_CPU=1``."""
    return _env_on("TRITON_INTERPRET") and _env_on("PLENOCTREE_TRITON_CPU")


def usable_anywhere() -> bool:
    """True when a Triton kernel can run on some tensors in this process (the probe
    :mod:`plenoctree.backend` registers the Triton backends with)."""
    # no torch import here (backend.resolve must not load it): without torch loaded there
    # are no CUDA tensors to run on, and interpreter mode needs none
    if not has_triton():
        return False
    if interpret_mode():
        return True
    return "torch" in sys.modules and triton_usable("cuda")


def triton_usable(device: Any) -> bool:
    """Whether a Triton kernel can run on tensors of ``device``.

    CUDA: ``triton`` importable and CUDA available. CPU: only in interpreter mode.
    """
    import torch

    dev = torch.device(device)
    if not has_triton():
        return False
    if dev.type == "cuda":
        return torch.cuda.is_available()
    return dev.type == "cpu" and interpret_mode()


def require_triton(device: Any, what: str) -> None:
    """Raise :class:`BackendError` naming what is missing when Triton cannot run on ``device``."""
    import torch

    if triton_usable(device):
        return
    dev = torch.device(device)
    if not has_triton():
        raise BackendError(f"{what}: backend 'triton' needs the triton package (shipped with "
                           "CUDA builds of torch; pip install triton)")
    if dev.type == "cpu":
        raise BackendError(f"{what}: backend 'triton' runs on CUDA tensors (or on CPU tensors "
                           "with TRITON_INTERPRET=1 PLENOCTREE_TRITON_CPU=1, for tests); got "
                           "CPU tensors")
    raise BackendError(f"{what}: backend 'triton' cannot run on {dev} (CUDA not available)")
