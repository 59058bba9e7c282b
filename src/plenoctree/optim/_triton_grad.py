"""Fine-tuning on the GPU: the Triton march kernel's forward and analytic backward as autograd.

:class:`TritonRenderFunction` is the GPU counterpart of
:class:`plenoctree.optim.autograd.OctreeRenderFunction` (numba): ``rgb [N, 3] = render(data)``
with the forward and the paper's analytic backward (B.3, eqs. 15 and 20; see
``render/_triton_impl.py``) both computed by ``_march_kernel``. The backward re-marches the rays
(same segments as the forward, no per-ray record is stored) and scatters into a dense gradient
with atomic adds, so float32 sums are reproducible to rounding, not bit for bit. Tested against
the torch twin's autograd gradient (in Triton's interpreter on CPU).
"""

from __future__ import annotations

from typing import Any

import torch

from ..render.options import KIND_RGBA, RenderOptions, parse_data_format

__all__ = ["TritonRenderFunction", "render_rays_triton_differentiable", "render_grad_backend"]


class TritonRenderFunction(torch.autograd.Function):
    """``forward(ctx, data, child, basis, geo, options, n_b) -> rgb [N, 3]``.

    ``data`` float32/float64 ``[n_nodes, 2, 2, 2, D]`` on the device; ``child`` int32
    ``[n_cells]``; ``basis [N, B]`` and ``geo [N, 14]`` from
    :func:`plenoctree.render._triton_impl.prepare_rays`. The gradient has the shape of ``data``.
    """

    @staticmethod
    def forward(ctx: Any, data: torch.Tensor, child: torch.Tensor, basis: torch.Tensor,
                geo: torch.Tensor, options: RenderOptions, n_b: int) -> torch.Tensor:
        from ..render._triton_impl import march_kernel_call

        d2 = data.detach().reshape(child.shape[0], data.shape[-1]).contiguous()
        rgb, _, _ = march_kernel_call(child, d2, basis, geo, options, n_b)
        ctx.save_for_backward(data, child, basis, geo, rgb)
        ctx.options, ctx.n_b = options, n_b
        return rgb

    @staticmethod
    def backward(ctx: Any, grad_rgb: torch.Tensor):
        from ..render._triton_impl import march_kernel_call

        data, child, basis, geo, rgb = ctx.saved_tensors
        if not ctx.needs_input_grad[0]:
            return None, None, None, None, None, None
        d2 = data.detach().reshape(child.shape[0], data.shape[-1]).contiguous()
        grad = march_kernel_call(child, d2, basis, geo, ctx.options, ctx.n_b,
                                 grad_rgb=grad_rgb.contiguous(), rgb_fwd=rgb)
        return grad.reshape(data.shape), None, None, None, None, None


def render_rays_triton_differentiable(data: torch.Tensor, tree: Any, origins: torch.Tensor,
                                      dirs: torch.Tensor, options: RenderOptions
                                      ) -> torch.Tensor:
    """``rgb [N, 3]`` of rays ``[N, 3]`` (on ``data``'s device) through ``tree`` with values
    ``data``; differentiable w.r.t. ``data`` (see :class:`TritonRenderFunction`)."""
    from ..render._torch_impl import ray_basis_torch
    from ..render._triton_impl import prepare_rays

    dev = data.device
    extra = getattr(tree, "extra_data", None)
    info = parse_data_format(tree.data_format, data.shape[-1], extra)
    child = torch.as_tensor(tree.child).to(device=dev, dtype=torch.int32).reshape(-1).contiguous()
    geo, unit = prepare_rays(tree.offset, tree.invradius, origins.to(dev), dirs.to(dev),
                             options.step_eps)
    basis = ray_basis_torch(info, unit, extra, options).to(data.dtype).contiguous()
    n_b = 1 if info.kind == KIND_RGBA else info.basis_dim
    return TritonRenderFunction.apply(data, child, basis, geo, options, n_b)


def render_grad_backend(data: torch.Tensor, tree: Any, o: torch.Tensor, d: torch.Tensor,
                        opts: RenderOptions) -> torch.Tensor:
    """Op ``render_grad`` of :mod:`plenoctree.backend` (``data`` on CUDA, or the CPU in
    Triton's interpreter)."""
    from .._triton import require_triton

    require_triton(data.device, "render_rays_differentiable")
    return render_rays_triton_differentiable(data, tree, o, d, opts)
