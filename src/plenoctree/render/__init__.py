"""Volume rendering of a PlenOctree: a torch twin (spec, autograd, CUDA) and a numba CPU kernel.

>>> out = render_rays(tree, origins, dirs)                  # doctest: +SKIP
>>> out.rgb.shape, out.depth.shape, out.alpha.shape         # doctest: +SKIP

Backends: ``"numba"`` (fast CPU kernel, compiled on first use and cached on disk),
``"triton"`` (the GPU kernel ``_triton_impl``, compiled by Triton on first use; CUDA tensors,
or CPU tensors under ``TRITON_INTERPRET=1`` for tests) and ``"torch"`` (the twin: vectorised
torch ops, differentiable, runs on CUDA tensors), chosen by :mod:`plenoctree.backend` (op
``"render"``): ``"auto"`` picks numba for CPU inputs, triton for CUDA tensors (the twin where
triton is missing). Importing this module compiles nothing: a kernel module is imported by the
first render that uses it.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from .. import backend as _backend
from .._util import to_numpy, vec3
from ..errors import ConfigError, TreeFormatError
from .options import FormatInfo, RenderOptions, RenderOutput, parse_data_format

__all__ = ["RenderOptions", "RenderOutput", "available_backends", "render_rays", "render_image",
           "tree_to_device", "CpuTree", "DeviceTree", "origin_in_reach"]

def available_backends(device: Any = None) -> list[str]:
    """Render backends usable here (on ``device`` when given), fastest first."""
    return _backend.backends("render", device)


def _rays_to_numpy_or_torch(name: str, x: Any) -> Any:
    if isinstance(x, torch.Tensor):
        if not x.is_floating_point():
            x = x.to(torch.float32)
        return x
    try:
        arr = np.asarray(x)
    except Exception:
        raise ConfigError(f"{name}: expected a numpy array or torch tensor, got "
                          f"{type(x).__name__}") from None
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise ConfigError(f"{name}: expected a float array, got dtype {arr.dtype}")
    return arr


def _check_rays(origins: Any, dirs: Any) -> None:
    for name, x in (("origins", origins), ("dirs", dirs)):
        if x.ndim < 1 or x.shape[-1] != 3:
            raise ConfigError(f"{name}: expected shape (..., 3), got {tuple(x.shape)}")
    if tuple(origins.shape) != tuple(dirs.shape):
        raise ConfigError(f"origins and dirs must have the same shape, got "
                          f"{tuple(origins.shape)} and {tuple(dirs.shape)}")
    for name, x in (("origins", origins), ("dirs", dirs)):
        finite = bool(torch.isfinite(x).all()) if isinstance(x, torch.Tensor) \
            else bool(np.isfinite(x).all())
        if not finite:
            raise ConfigError(f"{name}: contains NaN or infinite values")
    # Squared norms without a float64 copy (this check runs on every frame).
    sq = (dirs * dirs).sum(-1) if isinstance(dirs, torch.Tensor) \
        else np.einsum("...i,...i->...", dirs, dirs)
    if bool((sq <= 1e-24).any()):
        raise ConfigError("dirs: contains zero-length directions")


def origin_in_reach(tree: Any, point: Any) -> bool:
    """Whether a ray can start at the world ``point [3]`` of ``tree``: within
    ``MAX_RAY_ORIGIN`` tree units of its box (farther, a float64 step cannot advance and
    :func:`render_rays` refuses the ray; the box then spans under 1e-8 rad from there)."""
    from ..octree.limits import MAX_RAY_ORIGIN

    point = np.asarray(point, np.float64).reshape(1, 3)
    return _reach(vec3(tree.offset), vec3(tree.invradius), point) <= MAX_RAY_ORIGIN


def _reach(offset: np.ndarray, inv: np.ndarray, points: np.ndarray) -> float:
    """The largest tree coordinate (in magnitude) of world ``points [M, 3]`` (float64)."""
    return float(np.abs(offset + inv * points).max())


def _check_origins(origins: Any, offset: np.ndarray, inv: np.ndarray) -> None:
    """Ray origins within ``MAX_RAY_ORIGIN`` tree units of the box (else steps cannot advance)."""
    from ..octree.limits import MAX_RAY_ORIGIN

    if isinstance(origins, torch.Tensor):
        lo, hi = origins.detach().reshape(-1, 3).aminmax(dim=0) if origins.numel() else (None, None)
        if lo is None:
            return
        lo, hi = lo.cpu().double().numpy(), hi.cpu().double().numpy()
    else:
        if origins.size == 0:
            return
        flat = origins.reshape(-1, 3)
        lo, hi = flat.min(0).astype(np.float64), flat.max(0).astype(np.float64)
    far = _reach(offset, inv, np.stack([lo, hi]))
    if not far <= MAX_RAY_ORIGIN:
        raise ConfigError(f"origins: a ray starts at tree coordinate {far:.3g} (the tree "
                          f"box is [0, 1]^3; at most {MAX_RAY_ORIGIN:g}: farther, a float64 "
                          "step cannot advance); move the camera closer")


def _tree_info(tree: Any) -> FormatInfo:
    for attr in ("child", "data", "offset", "invradius", "data_format"):
        if not hasattr(tree, attr):
            raise ConfigError(f"render: expected an Octree, got {type(tree).__name__} "
                              f"without {attr!r}")
    child, data = tree.child, tree.data
    if child.ndim != 4 or tuple(child.shape[1:]) != (2, 2, 2):
        raise ConfigError(
            f"tree.child: expected shape (n_nodes, 2, 2, 2), got {tuple(child.shape)}")
    if data.ndim != 5 or tuple(data.shape[:4]) != tuple(child.shape):
        raise ConfigError(f"tree.data: expected shape ({child.shape[0]}, 2, 2, 2, D), got "
                          f"{tuple(data.shape)}")
    inv = np.asarray(tree.invradius.detach().cpu() if isinstance(tree.invradius, torch.Tensor)
                     else tree.invradius, dtype=np.float64).reshape(-1)
    if inv.shape != (3,) and inv.shape != (1,):
        raise ConfigError(f"tree.invradius: expected 3 values, got shape {inv.shape}")
    if not (np.isfinite(inv).all() and (inv > 0).all()):
        raise ConfigError(f"tree.invradius: must be finite and > 0, got {inv.tolist()}")
    from ..octree.check import check_box, check_child_cached
    try:
        check_box(vec3(tree.offset), inv if inv.size == 3 else np.repeat(inv, 3), "render: tree")
        if not isinstance(tree, CpuTree):   # a CpuTree's child: a private copy, checked once
            check_child_cached(tree, "render: tree")    # once per tree object and child version
    except TreeFormatError as e:
        raise ConfigError(str(e)) from None
    return parse_data_format(tree.data_format, data.shape[-1], getattr(tree, "extra_data", None))


def render_rays(tree: Any, origins: Any, dirs: Any, options: RenderOptions | None = None,
                backend: str = "auto") -> RenderOutput:
    """Render world-space rays through ``tree``.

    Args:
        tree: an :class:`~plenoctree.octree.Octree`.
        origins: ``[..., 3]`` ray origins, world units (numpy array or torch tensor).
        dirs: ``[..., 3]`` ray directions (any non-zero length; normalised internally).
        options: :class:`RenderOptions`; defaults when ``None``.
        backend: ``"auto"`` (numba for CPU inputs, triton for CUDA tensors, else torch),
            ``"numba"``, ``"triton"`` or ``"torch"`` (see :mod:`plenoctree.backend`; numba with
            CUDA tensors is an error).

    Returns:
        :class:`RenderOutput` of torch tensors ``rgb [..., 3]``, ``depth [...]`` (world units
        along the unit direction), ``alpha [...]``, on the device of torch inputs (CPU
        otherwise). The numba backend returns float32; the torch backend the dtype of
        ``tree.data`` (float16 is computed in float32).

    Raises:
        ConfigError: mismatched or non-(..., 3) shapes, NaN/inf, zero directions, bad options or
            a malformed tree. BackendError: an unknown backend or one that does not run on the
            inputs' device.
    """
    opts = (options if options is not None else RenderOptions())
    if not isinstance(opts, RenderOptions):
        raise ConfigError(f"options: expected RenderOptions, got {type(opts).__name__}")
    opts.validated()
    origins = _rays_to_numpy_or_torch("origins", origins)
    dirs = _rays_to_numpy_or_torch("dirs", dirs)
    _check_rays(origins, dirs)
    info = _tree_info(tree)
    device = next((x.device for x in (origins, dirs) if isinstance(x, torch.Tensor)),
                  torch.device("cpu"))
    name = _backend.resolve("render", backend, device)
    batch = tuple(origins.shape[:-1])
    _check_origins(origins, vec3(tree.offset), vec3(tree.invradius))
    # The numba kernel marches the pixels of an image in 2-D tiles when it knows the width.
    hint = {"width": int(batch[-1])} if name == "numba" and len(batch) >= 2 else {}
    out = _backend.implementation("render", name)(
        tree, info, origins.reshape(-1, 3), dirs.reshape(-1, 3), opts, device, **hint)
    return RenderOutput(rgb=out.rgb.reshape(*batch, 3).to(device),
                        depth=out.depth.reshape(batch).to(device),
                        alpha=out.alpha.reshape(batch).to(device))


def _numba_render(tree: Any, info: FormatInfo, origins: Any, dirs: Any, opts: RenderOptions,
                  device: Any, width: int = 0) -> RenderOutput:
    """The numba kernel on CPU inputs ``origins, dirs [N, 3]`` (numpy or CPU tensors);
    ``width``: the image width when the rays are an image's pixels in row-major order."""
    from . import _render_numba

    rgb, depth, alpha = _render_numba.render_rays_numba(
        _render_numba.prepare(tree, info, opts), to_numpy(origins), to_numpy(dirs), width=width)
    return RenderOutput(torch.from_numpy(rgb), torch.from_numpy(depth), torch.from_numpy(alpha))


def _render_torch(tree: Any, info: FormatInfo, origins: Any, dirs: Any, opts: RenderOptions,
                  device: Any) -> RenderOutput:
    """The torch twin on ``device`` (``origins, dirs [N, 3]``)."""
    from ._torch_impl import render_rays_torch

    data = tree.data
    if isinstance(data, torch.Tensor):
        data = data.to(device)
    else:
        data = torch.from_numpy(np.ascontiguousarray(data)).to(device)
    if data.dtype not in (torch.float32, torch.float64):
        data = data.float()
    o = origins if isinstance(origins, torch.Tensor) else torch.from_numpy(origins)
    d = dirs if isinstance(dirs, torch.Tensor) else torch.from_numpy(dirs)
    return render_rays_torch(tree, o, d, opts, data=data)


def _extra(tree: Any) -> Any:
    extra = getattr(tree, "extra_data", None)
    return None if extra is None else to_numpy(extra)


class DeviceTree:
    """A tree whose ``child``/``data`` are torch tensors on one device (see :func:`tree_to_device`).

    Same attributes as :class:`~plenoctree.octree.Octree` that the renderers read: ``child``
    int32 ``[n_nodes, 2, 2, 2]``, ``data`` float32 (float64 kept) ``[n_nodes, 2, 2, 2, D]``,
    ``offset``, ``invradius`` (numpy float64 ``[3]``), ``data_format``, ``extra_data``.
    """

    def __init__(self, tree: Any, device: Any) -> None:
        dev = torch.device(device)
        data = torch.as_tensor(np.asarray(tree.data) if not isinstance(tree.data, torch.Tensor)
                               else tree.data)
        if data.dtype != torch.float64:
            data = data.to(torch.float32)
        child = tree.child if isinstance(tree.child, torch.Tensor) else \
            torch.from_numpy(np.ascontiguousarray(tree.child))
        self.child = child.to(device=dev, dtype=torch.int32).contiguous()
        self.data = data.to(dev).contiguous()
        self.offset, self.invradius = vec3(tree.offset), vec3(tree.invradius)
        # the box on the device too: a frame's rays need it (an upload per frame otherwise)
        self.box = (torch.as_tensor(self.offset, device=dev),
                    torch.as_tensor(self.invradius, device=dev))
        self.data_format = tree.data_format
        self.extra_data = _extra(tree)
        self.device = dev


class CpuTree:
    """A tree prepared once for many frames on the CPU (see :func:`tree_to_device`).

    Same attributes as :class:`~plenoctree.octree.Octree` that the renderers read (``child``
    int32, a checked private copy, so frames skip the per-call topology fingerprint; ``data``
    float32 — the tree's own array when it already is one, not a copy —; ``offset``,
    ``invradius``, ``data_format``, ``extra_data``), plus ``empty_skip``: the numba renderer's
    empty-space skip tables (:mod:`.empty_skip`), made from the tree as it is now. It is a
    snapshot of the topology and of which leaves are empty: render an edited tree through a new
    one.
    """

    def __init__(self, tree: Any) -> None:
        from .empty_skip import skip_tables

        self.child = np.array(to_numpy(tree.child), dtype=np.int32, order="C")   # a copy
        self.data = np.ascontiguousarray(to_numpy(tree.data), dtype=np.float32)
        self.offset, self.invradius = vec3(tree.offset), vec3(tree.invradius)
        self.data_format = tree.data_format
        self.extra_data = _extra(tree)
        self.device = torch.device("cpu")
        n = self.child.shape[0] * 8
        self.empty_skip = skip_tables(self.child.reshape(n), self.data.reshape(n, -1))


def tree_to_device(tree: Any, device: Any) -> Any:
    """``tree`` prepared once for rendering many frames on ``device``: a :class:`DeviceTree`
    (its arrays on the GPU, so frames do not copy the tree) or, for the CPU, a
    :class:`CpuTree` (float32 arrays and the numba renderer's empty-space skip tables:
    the same images, fewer segments per ray)."""
    dev = torch.device(device)
    if dev.type == "cpu":
        if isinstance(tree, CpuTree):
            return tree
        _tree_info(tree)                     # a malformed tree fails here, not in the tables
        return CpuTree(tree)
    if isinstance(tree, DeviceTree) and tree.device == dev:
        return tree
    return DeviceTree(tree, dev)


def render_image(tree: Any, cameras: Any, index: int, options: RenderOptions | None = None,
                 backend: str = "auto", device: Any = None) -> RenderOutput:
    """Render camera ``index`` of ``cameras`` (a :class:`~plenoctree.datasets.Cameras`).

    ``device``: where to render (``None``/``"cpu"``: numpy rays on the CPU; ``"cuda"``: the
    rays are moved there, the outputs stay there and the call waits for the GPU, so timing it
    measures the render). Pass a tree from :func:`tree_to_device` to avoid copying the tree
    each frame.

    Returns a :class:`RenderOutput` with ``rgb [H, W, 3]``, ``depth [H, W]``, ``alpha [H, W]``.
    """
    if not hasattr(cameras, "rays"):
        raise ConfigError(f"cameras: expected a Cameras object, got {type(cameras).__name__}")
    dev = torch.device(device) if device is not None else torch.device("cpu")
    if dev.type == "cpu" and _backend.resolve("render", backend, dev) == "numba":
        return _numba_render_camera(tree, cameras, index, options)
    if dev.type == "cpu":
        origins, dirs = cameras.rays(index)
        return render_rays(tree, origins, dirs, options=options, backend=backend)
    # a device: the rays made there, nothing read back (._device)
    from ._device import render_camera_device

    opts = (options if options is not None else RenderOptions())
    if not isinstance(opts, RenderOptions):
        raise ConfigError(f"options: expected RenderOptions, got {type(opts).__name__}")
    opts.validated()
    info = _tree_info(tree)
    out = render_camera_device(tree_to_device(tree, dev), info, cameras, cameras._index(index),
                               opts, dev, _backend.resolve("render", backend, dev))
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)
    return out


def _numba_render_camera(tree: Any, cameras: Any, index: int,
                         options: RenderOptions | None) -> RenderOutput:
    """:func:`render_image` with the numba kernel making each pixel's ray itself (the same
    rays as ``cameras.rays(index)``; no per-frame ray arrays or ray checks over the image)."""
    from . import _render_numba

    opts = (options if options is not None else RenderOptions())
    if not isinstance(opts, RenderOptions):
        raise ConfigError(f"options: expected RenderOptions, got {type(opts).__name__}")
    opts.validated()
    info = _tree_info(tree)
    i = cameras._index(index)
    w, h = cameras.width, cameras.height
    # The corner pixels' rays bound every other one (directions are affine in the pixel, NDC
    # origins projective with a denominator of one sign): checking them checks the image.
    cols, rows = np.array([0, w - 1, 0, w - 1]), np.array([0, 0, h - 1, h - 1])
    o, d = cameras.pixel_rays(np.full(4, i), cols, rows)
    _check_rays(o, d)
    _check_origins(o, vec3(tree.offset), vec3(tree.invradius))
    cam = _render_numba.pack_cameras(cameras, [i])[0]

    rgb, depth, alpha = _render_numba.empty_outputs(w * h)
    _render_numba.render_camera_prepared(_render_numba.prepare(tree, info, opts), cam, w, h,
                                         (rgb, depth, alpha))
    return RenderOutput(torch.from_numpy(rgb.reshape(h, w, 3)), torch.from_numpy(depth.reshape(h, w)),
                        torch.from_numpy(alpha.reshape(h, w)))
