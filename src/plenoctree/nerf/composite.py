"""Op ``composite``: eq. (1)–(2) of packed samples at a fixed step, with the per-ray sums a
training step needs and the distortion loss, fused — one kernel launch forward and one
backward (the torch twin takes ~40 ops forward and backward), as in nerfacc.

For ray ``r`` with samples ``i`` (``offsets[r] ≤ i < offsets[r + 1]``, increasing ``t``),
``τ_i = σ_i δ``, ``T_i = exp(-Σ_{k<i} τ_k)``, ``w_i = T_i (1 - e^{-τ_i})``, ``W_i = Σ_{k<i} w_k``,
``S_i = Σ_{k<i} w_k t_k``::

    out[r] = (Σ w_i c_i [3],  Σ w_i,  Σ w_i t_i,  Σ_i 2 w_i (t_i W_i - S_i) + δ/3 Σ w_i²)

(colour before the background, opacity, unnormalised depth, the distortion loss of
:func:`.volrend.distortion_packed`). The backward pass is analytic: with
``g_i = ∂L/∂w_i`` (the other weights held fixed)::

    g_i = ∇c·c_i + ∇a + ∇d t_i + ∇l (2 (2 (t_i W_i - S_i) + S - t_i W) + 2δ/3 w_i)
    ∂L/∂σ_i = δ (T_{i+1} g_i - Σ_{j>i} w_j g_j),   ∂L/∂c_i = w_i ∇c

(``W``, ``S``: the ray's totals). The suffix sum is ``G - Σ_{j≤i} w_j g_j`` with
``G = Σ_j w_j g_j``, in which the totals' terms cancel, so each ray is two passes over its
samples. Backends (:mod:`plenoctree.backend`): numba (CPU, float64 accumulation), Triton
(CUDA, float32) and the twin :func:`_composite_torch` (:mod:`.volrend`'s functions under
autograd).
"""

from __future__ import annotations

import torch

from .volrend import composite_packed, distortion_packed, render_weights_packed

__all__ = ["composite_rays"]


def _composite_torch(sigma: torch.Tensor, color: torch.Tensor, t: torch.Tensor,
                     offsets: torch.Tensor, step: float, dist: bool) -> torch.Tensor:
    """The twin: ``out [R, 6]`` by :mod:`.volrend`'s packed functions (autograd backward)."""
    n = offsets.shape[0] - 1
    m = sigma.shape[0]
    slots = torch.arange(m, device=sigma.device)
    ray_idx = (torch.searchsorted(offsets, slots, right=True) - 1).clamp(0, max(n - 1, 0))
    inside = (slots < offsets[-1]) & (slots >= offsets[0])
    sig = sigma.float() * inside
    w, _ = render_weights_packed(sig, step, ray_idx, offsets)
    vals = torch.cat([color.float(), torch.ones_like(t)[:, None], t[:, None]], 1)
    sums = composite_packed(w * inside, vals, ray_idx, n)
    loss = (distortion_packed(w * inside, t, step, ray_idx, offsets, n) if dist
            else torch.zeros_like(sums[:, 0]))
    return torch.cat([sums, loss[:, None]], 1)


class _Composite(torch.autograd.Function):
    """The fused forward and analytic backward of one backend (``kernels``: ``(forward,
    backward)`` taking and returning tensors on the inputs' device)."""

    @staticmethod
    def forward(ctx, sigma, color, t, offsets, step, dist, kernels):
        fwd, _ = kernels
        s = sigma.detach().float().contiguous()
        c = color.detach().float().contiguous()
        tt = t.detach().float().contiguous()
        off = offsets.contiguous()
        out = fwd(s, c, tt, off, step, dist)
        ctx.save_for_backward(s, c, tt, off)
        ctx.step, ctx.kernels = step, kernels
        ctx.dtypes = (sigma.dtype, color.dtype)
        return out

    @staticmethod
    def backward(ctx, grad_out):
        s, c, tt, off = ctx.saved_tensors
        _, bwd = ctx.kernels
        g_s, g_c = bwd(s, c, tt, off, ctx.step, grad_out.float().contiguous())
        return g_s.to(ctx.dtypes[0]), g_c.to(ctx.dtypes[1]), None, None, None, None, None


def _numba_forward(sigma, color, t, offsets, step, dist):
    from . import _composite_numba as K
    return torch.from_numpy(K.run_forward(sigma.numpy(), color.numpy(), t.numpy(),
                                          offsets.numpy(), step, dist))


def _numba_backward(sigma, color, t, offsets, step, grad_out):
    from . import _composite_numba as K
    g_s = torch.zeros_like(sigma)
    g_c = torch.zeros_like(color)
    K.composite_backward(sigma.numpy(), color.numpy(), t.numpy(), offsets.numpy(),
                         float(step), grad_out.numpy(), g_s.numpy(), g_c.numpy())
    return g_s, g_c


def _composite_numba(sigma, color, t, offsets, step, dist):
    return _Composite.apply(sigma, color, t, offsets, float(step), bool(dist),
                            (_numba_forward, _numba_backward))


def _composite_triton(sigma, color, t, offsets, step, dist):
    from ._composite_triton import composite_backend
    return _Composite.apply(sigma, color, t, offsets, float(step), bool(dist),
                            composite_backend)


def composite_rays(sigma: torch.Tensor, color: torch.Tensor, t: torch.Tensor,
                   offsets: torch.Tensor, step: float, distortion: bool = False,
                   backend: str = "auto") -> dict:
    """Composite packed samples at a fixed step (see the module doc).

    Args:
        sigma: ``[M]`` densities (1/world unit); color: ``[M, 3]`` in [0, 1]; t: ``[M]``
            distances (world units) of samples stored ray after ray, increasing within a ray.
        offsets: int64 ``[R + 1]``, non-decreasing: ray ``r`` owns ``offsets[r]:offsets[r + 1]``
            (slots outside ``offsets[0]:offsets[-1]`` belong to no ray: no output, no gradient).
        step: the segment length δ (world units). distortion: also the distortion loss.
        backend: "auto" (numba on CPU, Triton on CUDA), "numba", "triton" or "torch".

    Returns:
        ``rgb [R, 3]`` (before the background), ``acc [R]``, ``dsum [R]`` (``Σ w t``) and with
        ``distortion`` ``distortion [R]``; float32, differentiable w.r.t. ``sigma`` and
        ``color``.
    """
    from .. import backend as _backend

    name = _backend.resolve("composite", backend, sigma.device)
    out = _backend.implementation("composite", name)(sigma, color, t, offsets, float(step),
                                                     bool(distortion))
    r = {"rgb": out[:, :3], "acc": out[:, 3], "dsum": out[:, 4]}
    if distortion:
        r["distortion"] = out[:, 5]
    return r
