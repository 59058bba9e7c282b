"""One backend policy: which implementation of a kernel runs, for every op that has several.

Every fast kernel has a slow torch twin it is tested against. The choice between them is made
here and nowhere else, with one rule:

- ``"auto"`` picks the highest-priority registered backend that runs on the inputs' device
  type (numba for CPU inputs, torch for CUDA ones until a GPU kernel is registered);
- an explicit name runs that backend; an unknown name, or a backend that does not run on the
  inputs' device (numba with CUDA tensors), raises :class:`~plenoctree.errors.BackendError`
  listing what is available there. Nothing falls back silently and nothing copies tensors
  between devices behind the caller's back.

Ops and the signature of their implementations (each call site documents the shapes):

===============  ==========================================================================
``render``       ``fn(tree, info, origins [N,3], dirs [N,3], opts, device) -> RenderOutput``
                 (flat ``[N]`` outputs) — :func:`plenoctree.render.render_rays`
``render_grad``  ``fn(data, tree, origins [N,3], dirs [N,3], opts) -> rgb [N,3]``,
                 differentiable w.r.t. ``data`` — :mod:`plenoctree.optim.autograd`
``finetune``     ``fn(data2 [cells, D], tree, options, optimizer, lr) -> stepper`` —
                 :func:`plenoctree.optim._steppers.make_stepper`
``visibility``   ``fn(sigma, spec, cand, origins, dirs, out, ray_chunk) -> out`` —
                 :func:`plenoctree.convert.visibility.max_ray_weights`
``hashgrid``     ``fn(encoding, points [N,3] world) -> features [N, L*F]`` —
                 :class:`plenoctree.nerf.encoding.HashGridEncoding`
``march``        ``fn(rays: MarchRays, grid: MarchGrid, max_per_ray) -> PackedSamples`` —
                 :func:`plenoctree.nerf.sampling.march_rays`
``march_fixed``  ``fn(rays: MarchRays, grid: MarchGrid, capacity) -> FixedSamples`` —
                 :func:`plenoctree.nerf.fixed.march_fixed`
``sh_colors``    ``fn(coeffs [N,3B], dirs [N,3], degree) -> rgb [N,3]`` —
                 :func:`plenoctree.nerf.model.sh_colors`
``composite``    ``fn(sigma [M], color [M,3], t [M], offsets [R+1], step, dist) -> [R,6]``,
                 differentiable — :func:`plenoctree.nerf.composite.composite_rays`
``ray_batch``    ``fn(source: RaySource, u [R,4] float64, bbox [2,3]) -> TrainRays`` —
                 :func:`plenoctree.nerf.raygen.ray_batch`
``mlp``          ``fn(field, points [N,3], dirs [N,3] | None) -> sigma [N] | (sigma, rgb)``,
                 differentiable — :meth:`plenoctree.nerf.model.RadianceField.radiance`
                 (no numba kernel: the twin is the eager network, numba inside on the CPU)
``terminate``    ``fn(cand: FixedSamples, sigma [k S], grid, stop_thresh, S) -> FixedSamples`` —
                 :func:`plenoctree.nerf.fixed.terminate_fixed` (no numba kernel)
===============  ==========================================================================

Adding a kernel (e.g. a Triton or CUDA renderer for CUDA tensors) is one registration, made
when the kernel's module is imported (import it from the op's package ``__init__`` so that it
is registered before first use)::

    register_backend("render", "triton", "plenoctree.render._triton_impl:render_rays_triton",
                     devices=("cuda",), priority=20, available=lambda: has_module("triton"))

``impl`` may be a callable or a lazy ``"module:attr"`` reference (nothing is imported, nothing
compiled, until the backend is first used). This module imports neither torch nor numba.
"""

from __future__ import annotations

import importlib
import importlib.util
from dataclasses import dataclass
from typing import Any, Callable

from . import _triton
from .errors import BackendError

__all__ = ["Backend", "register_backend", "resolve", "implementation", "backends", "ops",
           "device_type", "check_name", "has_module"]


@dataclass(frozen=True)
class Backend:
    """One implementation of ``op``.

    ``devices``: the device types (``torch.device.type``: ``"cpu"``, ``"cuda"``) it takes
    inputs on. ``priority``: ``"auto"`` takes the highest among those that run on the device.
    ``impl``: the callable, or ``"module:attr"`` imported on first use. ``available``: a
    check that the backend can run here (a package is installed), ``None`` = always.
    """

    op: str
    name: str
    impl: Callable[..., Any] | str
    devices: tuple[str, ...] = ("cpu",)
    priority: int = 0
    available: Callable[[], bool] | None = None

    def usable(self) -> bool:
        return self.available is None or bool(self.available())


_REGISTRY: dict[str, dict[str, Backend]] = {}
_LOADED: dict[tuple[str, str], Callable[..., Any]] = {}


def has_module(name: str) -> bool:
    """True when ``name`` is importable (without importing it)."""
    return importlib.util.find_spec(name) is not None


def register_backend(op: str, name: str, impl: Callable[..., Any] | str,
                     devices: tuple[str, ...] | list[str] = ("cpu",), priority: int = 0,
                     available: Callable[[], bool] | None = None) -> Backend:
    """Register (or replace) backend ``name`` of ``op``; returns the entry."""
    name = str(name).lower()
    if name == "auto":
        raise ValueError("'auto' is not a backend name")
    entry = Backend(op, name, impl, tuple(devices), int(priority), available)
    _REGISTRY.setdefault(op, {})[name] = entry
    _LOADED.pop((op, name), None)
    return entry


def ops() -> list[str]:
    """Every op with registered backends."""
    return sorted(_REGISTRY)


def _entries(op: str) -> dict[str, Backend]:
    try:
        return _REGISTRY[op]
    except KeyError:
        raise BackendError(f"unknown op {op!r}; ops with backends: {', '.join(ops())}") from None


def backends(op: str, device: str | None = None) -> list[str]:
    """Usable backends of ``op`` (on ``device``'s type when given), ``auto``'s order first."""
    dev = None if device is None else device_type(device)
    found = [b for b in _entries(op).values()
             if b.usable() and (dev is None or dev in b.devices)]
    return [b.name for b in sorted(found, key=lambda b: -b.priority)]


def device_type(x: Any) -> str:
    """Device type of ``x``: a ``torch.device``, a device string, a tensor (``.device``), or
    anything else (numpy arrays, ``None``) = ``"cpu"``."""
    if isinstance(x, str):
        return x.split(":")[0].lower()
    dev = getattr(x, "device", None)
    if dev is not None and hasattr(dev, "type"):
        return str(dev.type)
    if hasattr(x, "type") and isinstance(getattr(x, "type"), str):
        return x.type
    return "cpu"


def check_name(op: str, requested: str) -> str:
    """``requested`` lower-cased when it is ``"auto"`` or a registered backend of ``op``,
    else :class:`BackendError` listing the backends (for options validated up front)."""
    name = str(requested).lower()
    entries = _entries(op)
    if name != "auto" and name not in entries:
        raise BackendError(f"{op}: unknown backend {requested!r}; available: "
                           f"{', '.join(['auto'] + backends(op))}")
    return name


def resolve(op: str, requested: str = "auto", device: Any = "cpu") -> str:
    """The backend of ``op`` that runs for inputs on ``device`` (see the module's rule)."""
    name = check_name(op, requested)
    dev = device_type(device)
    here = backends(op, dev)
    if name == "auto":
        if dev == "cpu":        # CPU tensors reach Triton (its interpreter) only by name
            here = [b for b in here if b != "triton"]
        if not here:
            raise BackendError(f"{op}: no backend runs on {dev}; registered: "
                               f"{', '.join(_entries(op))}")
        return here[0]
    entry = _entries(op)[name]
    if not entry.usable():
        raise BackendError(f"{op}: backend {name!r} cannot run here (its package is missing); "
                           f"available: {', '.join(backends(op)) or 'none'}")
    if dev not in entry.devices:
        raise BackendError(f"{op}: backend {name!r} runs on {'/'.join(entry.devices)} inputs, "
                           f"got {dev}; available on {dev}: {', '.join(here) or 'none'}")
    return name


def implementation(op: str, name: str) -> Callable[..., Any]:
    """The callable of backend ``name`` of ``op`` (a resolved name), imported on first use."""
    key = (op, name)
    fn = _LOADED.get(key)
    if fn is None:
        entry = _entries(op).get(name)
        if entry is None:
            raise BackendError(f"{op}: unknown backend {name!r}; available: "
                               f"{', '.join(backends(op))}")
        fn = entry.impl
        if isinstance(fn, str):
            mod, _, attr = fn.partition(":")
            fn = getattr(importlib.import_module(mod), attr)
        _LOADED[key] = fn
    return fn


def run(op: str, requested: str, device: Any, *args: Any, **kwargs: Any) -> Any:
    """``implementation(op, resolve(op, requested, device))(*args, **kwargs)``."""
    return implementation(op, resolve(op, requested, device))(*args, **kwargs)


# Built-in backends: numba kernels (CPU, required dependency) and their torch twins (any device).
_NUMBA, _TORCH = 10, 0
for _op, _numba, _torch in (
    ("render", "plenoctree.render:_numba_render", "plenoctree.render:_render_torch"),
    ("render_grad", "plenoctree.optim.autograd:_grad_numba",
     "plenoctree.optim.autograd:_grad_torch"),
    ("finetune", "plenoctree.optim._steppers:_numba_stepper",
     "plenoctree.optim._steppers:TorchStepper"),
    ("visibility", "plenoctree.convert.visibility:_max_weights_numba_run",
     "plenoctree.convert.visibility:_max_weights_torch_run"),
    ("hashgrid", "plenoctree.nerf.encoding:_hashgrid_numba_run",
     "plenoctree.nerf.encoding:_hashgrid_torch_run"),
    ("march", "plenoctree.nerf.sampling:_march_numba", "plenoctree.nerf.sampling:_march_torch"),
    ("march_fixed", "plenoctree.nerf.fixed:_march_fixed_numba",
     "plenoctree.nerf.fixed:_march_fixed_torch"),
    ("sh_colors", "plenoctree.nerf.model:_sh_colors_numba_run",
     "plenoctree.nerf.model:_sh_colors_torch"),
    ("composite", "plenoctree.nerf.composite:_composite_numba",
     "plenoctree.nerf.composite:_composite_torch"),
    ("ray_batch", "plenoctree.nerf.raygen:_ray_batch_numba",
     "plenoctree.nerf.raygen:_ray_batch_torch"),
):
    register_backend(_op, "numba", _numba, devices=("cpu",), priority=_NUMBA)
    register_backend(_op, "torch", _torch, devices=("cpu", "cuda"), priority=_TORCH)
del _op, _numba, _torch
# no numba kernel: on the CPU the twin runs (the eager network; torch prefix sums)
register_backend("mlp", "torch", "plenoctree.nerf.model:_mlp_torch", devices=("cpu", "cuda"),
                 priority=_TORCH)
register_backend("terminate", "torch", "plenoctree.nerf.fixed:_terminate_torch",
                 devices=("cpu", "cuda"), priority=_TORCH)

# GPU kernels (Triton; CUDA tensors, or CPU tensors in Triton's interpreter): see _triton.py.
for _op, _impl in _triton.TRITON_IMPLS:
    register_backend(_op, "triton", _impl, devices=("cuda", "cpu"),
                     priority=_triton.TRITON_PRIORITY, available=_triton.usable_anywhere)
del _op, _impl
