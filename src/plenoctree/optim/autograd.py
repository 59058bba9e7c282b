"""Differentiable octree rendering with respect to the cell data.

:func:`render_rays_differentiable` renders rays through a tree whose values come from a torch
tensor and returns a colour that autograd can differentiate with respect to that tensor:

- ``backend="numba"`` (CPU tensors): :class:`OctreeRenderFunction`, a ``torch.autograd.Function``
  whose forward and backward are numba kernels; the backward uses the paper's analytic
  derivatives (B.3: eq. 15 for colour through the basis and the sigmoid, eq. 20 for σ with the
  suffix sums, zero where σ ≤ 0) and scatters race-free into per-thread slabs;
- ``backend="triton"`` (CUDA tensors): :class:`~plenoctree.optim._triton_grad.TritonRenderFunction`,
  the same analytic forward/backward as one Triton GPU kernel (atomic scatter);
- ``backend="torch"``: the renderer's torch twin with plain autograd (the oracle; runs on CUDA).

Example::

    >>> data = torch.tensor(tree.data, requires_grad=True)          # doctest: +SKIP
    >>> rgb = render_rays_differentiable(data, tree, origins, dirs)  # doctest: +SKIP
    >>> ((rgb - target) ** 2).mean().backward()                      # doctest: +SKIP
    >>> data.grad.shape == data.shape                                # doctest: +SKIP
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from .. import backend as _backend
from ..errors import ConfigError
from ..render import RenderOptions

__all__ = ["OctreeRenderFunction", "render_rays_differentiable", "differentiable_backends"]


def differentiable_backends() -> list[str]:
    """Backends :func:`render_rays_differentiable` can use here, fastest first."""
    return _backend.backends("render_grad")


class OctreeRenderFunction(torch.autograd.Function):
    """``rgb [N, 3] = render(data)`` with numba forward and analytic numba backward.

    ``forward(ctx, data, args, origins, dirs)``: ``data`` float32/float64 CPU tensor
    ``[n_nodes, 2, 2, 2, D]``; ``args`` a :class:`~plenoctree.render._spec.TreeSpec` (tree
    geometry and options); ``origins, dirs`` float32 numpy ``[N, 3]``. The gradient has the
    shape of ``data``; cells no ray reaches with σ > 0 (and every internal cell) get 0.
    """

    @staticmethod
    def forward(ctx: Any, data: torch.Tensor, args: Any, origins: np.ndarray,
                dirs: np.ndarray) -> torch.Tensor:
        from ._render_grad import forward_numba

        data2 = data.detach().contiguous().reshape(args.n_cells, data.shape[-1]).numpy()
        rgb = forward_numba(args, data2, origins, dirs)
        ctx.save_for_backward(data)
        ctx.args, ctx.origins, ctx.dirs = args, origins, dirs
        return torch.from_numpy(rgb)

    @staticmethod
    def backward(ctx: Any, grad_rgb: torch.Tensor):
        from ._render_grad import backward_numba

        (data,) = ctx.saved_tensors
        if not ctx.needs_input_grad[0]:
            return None, None, None, None
        data2 = data.detach().contiguous().reshape(ctx.args.n_cells, data.shape[-1]).numpy()
        g = grad_rgb.detach().to(torch.float64).contiguous().numpy()
        buf = backward_numba(ctx.args, data2, ctx.origins, ctx.dirs, g)
        grad = torch.from_numpy(buf.grad).reshape(data.shape)
        return grad, None, None, None


def _check_data(data: Any, tree: Any) -> torch.Tensor:
    if not isinstance(data, torch.Tensor):
        raise ConfigError(f"data: expected a torch tensor, got {type(data).__name__}")
    want = tuple(tree.child.shape) + (int(tree.data.shape[-1]),)
    if tuple(data.shape) != want:
        raise ConfigError(f"data: expected shape {want} (the tree's data), got {tuple(data.shape)}")
    if data.dtype not in (torch.float32, torch.float64):
        raise ConfigError(f"data: expected float32 or float64, got {data.dtype}")
    from ..errors import TreeFormatError
    from ..octree.check import check_box, check_child_cached

    try:                         # in-memory trees: topology once per tree object and version
        off, inv = (np.broadcast_to(np.asarray(v.detach().cpu() if hasattr(v, "detach") else v,
                                               np.float64).reshape(-1), (3,))
                    for v in (tree.offset, tree.invradius))
        check_box(off, inv, "render: tree")
        check_child_cached(tree, "render: tree")
    except TreeFormatError as e:
        raise ConfigError(str(e)) from None
    return data


def render_rays_differentiable(data: torch.Tensor, tree: Any, origins: Any, dirs: Any,
                               options: RenderOptions | None = None,
                               backend: str = "auto") -> torch.Tensor:
    """Render rays through ``tree`` with cell values ``data``; differentiable w.r.t. ``data``.

    Args:
        data: ``[n_nodes, 2, 2, 2, D]`` float32/float64 tensor (usually ``requires_grad``)
            used in place of ``tree.data``; σ enters as ``relu(σ)``.
        tree: the :class:`~plenoctree.octree.Octree` giving the structure (``child``), the box
            (``offset``, ``invradius``) and the format; its own ``data`` is not read.
        origins, dirs: ``[..., 3]`` world-space rays (numpy or torch; dirs normalised inside).
        options: :class:`~plenoctree.render.RenderOptions` (early stop, background, basis range).
        backend: ``"auto"`` (numba for CPU tensors, triton for CUDA ones, else torch),
            ``"numba"``, ``"triton"`` or ``"torch"`` (the twin, plain autograd).

    Returns:
        ``rgb [..., 3]`` in the dtype and on the device of ``data``: ``Σ w c + T_N · background``.
    """
    opts = options if options is not None else RenderOptions()
    if not isinstance(opts, RenderOptions):
        raise ConfigError(f"options: expected RenderOptions, got {type(opts).__name__}")
    opts.validated()
    if opts.renormalize:        # the analytic gradients are those of the exact rule
        raise ConfigError("differentiable rendering uses the exact colour rule: "
                          "RenderOptions.renormalize must be False")
    data = _check_data(data, tree)
    o = origins if isinstance(origins, torch.Tensor) else torch.as_tensor(np.asarray(origins))
    d = dirs if isinstance(dirs, torch.Tensor) else torch.as_tensor(np.asarray(dirs))
    if o.ndim < 1 or o.shape[-1] != 3 or tuple(o.shape) != tuple(d.shape):
        raise ConfigError(f"origins/dirs: expected equal shapes (..., 3), got {tuple(o.shape)} "
                          f"and {tuple(d.shape)}")
    batch = tuple(o.shape[:-1])
    name = _backend.resolve("render_grad", backend, data.device)
    rgb = _backend.implementation("render_grad", name)(data, tree, o.reshape(-1, 3),
                                                       d.reshape(-1, 3), opts)
    return rgb.reshape(*batch, 3)


def _grad_numba(data: torch.Tensor, tree: Any, o: torch.Tensor, d: torch.Tensor,
                opts: RenderOptions) -> torch.Tensor:
    """numba forward + analytic backward (CPU tensors)."""
    from ._render_grad import _rays, kernel_args

    args = kernel_args(tree, opts)
    o_np, d_np = _rays(o, d)
    return OctreeRenderFunction.apply(data, args, o_np, d_np)


def _grad_torch(data: torch.Tensor, tree: Any, o: torch.Tensor, d: torch.Tensor,
                opts: RenderOptions) -> torch.Tensor:
    """The renderer's torch twin with plain autograd (any device)."""
    from ..render._torch_impl import render_rays_torch

    return render_rays_torch(tree, o, d, opts, data=data).rgb
