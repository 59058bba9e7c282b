"""The torch twin of the octree renderer: the executable spec and the autograd oracle.

Vectorised over rays: all rays march together, one voxel segment per step; each step descends
the tree from the root (a depth-limited batched loop). Differentiable with respect to ``data``
(pass a tensor with ``requires_grad``), works in float32 or float64 and on CUDA tensors.
Colours, weights and outputs use the dtype of ``data``; the ray geometry (tree-space positions,
distances, leaf lookup) is always float64, as in the numba kernel, so both backends pick the
same leaves even for rays running exactly along voxel faces.

Algorithm (both backends; the numba kernel in ``_render_numba`` computes the same thing):

1. ``d ← d / |d|``; tree-space origin ``o' = offset + invradius * o`` and per-unit-``t``
   direction ``d' = invradius * d``, so the tree-space point at world distance ``t`` is
   ``p(t) = o' + t d'`` (anisotropic ``invradius`` allowed).
2. ``[t0, t1]`` = intersection of the ray with the box ``[0, 1]^3``, ``t0 ≥ 0``.
3. Starting at ``t = t0``: locate the leaf containing ``p(t + ε_t)``, ``ε_t = step_eps / |d'|``
   (points are quantised to integer coordinates ``floor(p * 2**QUANT_BITS)``; the bit
   ``QUANT_BITS - 1 - l`` of each coordinate picks the cell at level ``l``); the segment ends at
   ``t' = min(max(exit(leaf), t + ε_t), t1)``, with ``δ = t' - t`` in world units (and
   ``t' > t`` by at least one float64 ulp: every step advances).
4. A segment with σ > 0 adds weight ``w = T (1 - exp(-σ δ))``, colour ``c`` and depth ``t_mid``;
   ``T *= exp(-σ δ)``; the ray stops when ``T < stop_thresh`` or ``t' = t1``. σ ≤ 0 adds
   nothing (and has zero gradient).
   A ray also stops after ``max_steps(D)`` segments (``octree.limits``: ``3·2^(D+1) + 64``,
   at most ``2^20``; D = deepest cell depth met so far), as the WebGL shader caps it.
5. ``rgb = Σ w c + T·background``, ``depth = Σ w t_mid / max(Σ w, 1e-10)``, ``alpha = 1 - T``;
   with ``renormalize`` (svox's ``fast`` rule) a ray stopped early (``T < stop_thresh``) gets
   ``rgb = Σ w c / (1 - T)`` and ``alpha = 1`` instead.

Colour ``c = sigmoid(Σ_{b in [sh_min, sh_max]} k_b Y_b(d))`` per channel: SH bases, SG bases
from ``extra_data`` (sharpness, mu) or, for RGBA, the single constant basis 1.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from ..sh import eval_sg_bases, eval_sh_bases
from ..octree.limits import MAX_DEPTH, max_steps
from .options import (KIND_RGBA, KIND_SG, KIND_SH, QUANT_BITS, FormatInfo, RenderOptions,
                      RenderOutput, parse_data_format)

__all__ = ["render_rays_torch", "ray_basis_torch", "box_intersect_torch"]

_SCALE = float(2 ** QUANT_BITS)
_BIG = 1e30


def ray_basis_torch(info: FormatInfo, dirs: torch.Tensor, extra_data: Any,
                    options: RenderOptions) -> torch.Tensor:
    """Basis values ``[N, B]`` for unit directions ``dirs [N, 3]``, zero outside the used range."""
    if info.kind == KIND_SH:
        basis = eval_sh_bases(info.sh_degree, dirs)
    elif info.kind == KIND_SG:
        extra = torch.as_tensor(extra_data, dtype=dirs.dtype, device=dirs.device)
        basis = eval_sg_bases(extra[:, 1:4], extra[:, 0], dirs)
    else:
        basis = torch.ones(dirs.shape[0], 1, dtype=dirs.dtype, device=dirs.device)
    lo, hi = options.basis_range(info.basis_dim)
    idx = torch.arange(info.basis_dim, device=dirs.device)
    keep = ((idx >= lo) & (idx <= hi)).to(dirs.dtype)
    return basis * keep


def box_intersect_torch(o_t: torch.Tensor, d_t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Entry/exit distances ``t0, t1`` [N] of rays ``o_t + t d_t`` with ``[0, 1]^3``, ``t0 >= 0``.

    A miss gives ``t0 >= t1``. Axes with ``d_t == 0`` restrict nothing when the origin lies
    inside the slab, and make the ray miss otherwise.
    """
    zero = d_t == 0
    inv = 1.0 / torch.where(zero, torch.ones_like(d_t), d_t)
    ta = (0.0 - o_t) * inv
    tb = (1.0 - o_t) * inv
    inside = (o_t >= 0.0) & (o_t <= 1.0)
    lo = torch.where(zero, torch.where(inside, -_BIG, _BIG), torch.minimum(ta, tb))
    hi = torch.where(zero, torch.where(inside, _BIG, -_BIG), torch.maximum(ta, tb))
    t0 = torch.clamp(lo.amax(dim=-1), min=0.0)
    t1 = hi.amin(dim=-1)
    return t0, t1


def _norm_no_overflow(v: torch.Tensor) -> torch.Tensor:
    """``|v|`` over the last axis, scaled where squaring would overflow or underflow."""
    n = torch.linalg.vector_norm(v, dim=-1)
    bad = ~torch.isfinite(n) | (n == 0)
    if bool(bad.any()):
        m = v.abs().amax(dim=-1, keepdim=True).clamp_min(torch.finfo(v.dtype).tiny)
        n = torch.where(bad, m[..., 0] * torch.linalg.vector_norm(v / m, dim=-1), n)
    return n


def _as_tensor(x: Any, dtype: torch.dtype | None, device: torch.device) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x.to(device=device, dtype=dtype if dtype is not None else x.dtype)
    return torch.as_tensor(np.asarray(x), device=device, dtype=dtype)


def _locate_leaves(child_flat: torch.Tensor, qi: torch.Tensor, max_levels: int
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """Batched descent from the root to the leaves holding the integer points ``qi [n, 3]``:
    returns their flat ``cell`` indices and depths ``level`` ``[n]``."""
    shifts = torch.tensor([4, 2, 1], device=qi.device)
    node = torch.zeros(qi.shape[0], dtype=torch.int64, device=qi.device)
    level = torch.zeros_like(node)
    for _ in range(max_levels):
        bits = (qi >> (QUANT_BITS - 1 - level)[:, None]) & 1
        cell = node * 8 + (bits * shifts).sum(-1)
        step = child_flat[cell]
        if not bool((step != 0).any()):
            return cell, level
        node = node + step
        level = level + (step != 0).to(torch.int64)
    raise ValueError(f"octree deeper than MAX_DEPTH = {MAX_DEPTH} is not supported")


def _values(data: Any) -> torch.Tensor:
    """``data`` as a float32 or float64 tensor (float16 and integers computed in float32)."""
    if not isinstance(data, torch.Tensor):
        data = torch.as_tensor(np.asarray(data, dtype=np.float32))
    if data.dtype not in (torch.float32, torch.float64):
        data = data.float()
    return data


def render_rays_torch(tree: Any, origins: Any, dirs: Any, options: RenderOptions | None = None,
                      data: Any = None) -> RenderOutput:
    """Render rays through an octree with plain torch ops (differentiable w.r.t. ``data``).

    Args:
        tree: an :class:`~plenoctree.octree.Octree` or anything with its attributes: ``child``
            int ``[n_nodes, 2, 2, 2]`` relative child offsets (0 = leaf), ``offset`` and
            ``invradius`` (``[3]``; tree coordinate = ``offset + invradius * world``),
            ``data_format`` (``"SH1".."SH25"``, ``"SG<B>"`` or ``"RGBA"``), ``extra_data`` (SG
            only, ``[B, 4]``: sharpness, mu_x, mu_y, mu_z) and, unless ``data`` is given,
            ``data``. Tensors or arrays.
        origins, dirs: ``[N, 3]`` world-space rays (dirs need not be unit length).
        options: :class:`RenderOptions` (defaults if ``None``).
        data: float ``[n_nodes, 2, 2, 2, D]`` values rendered instead of ``tree.data`` (e.g. a
            tensor with ``requires_grad``: gradients flow into it). Its dtype (float32/float64)
            and device set the computation's.

    Returns:
        :class:`RenderOutput` with ``rgb [N, 3]``, ``depth [N]``, ``alpha [N]`` in the dtype and on
        the device of ``data``.
    """
    opts = (options or RenderOptions()).validated()
    data = _values(tree.data if data is None else data)
    device, dtype = data.device, data.dtype
    n_nodes, d_dim = data.shape[0], data.shape[-1]
    extra_data = getattr(tree, "extra_data", None)
    info = parse_data_format(tree.data_format, d_dim, extra_data)
    child_flat = _as_tensor(tree.child, torch.int64, device).reshape(-1)
    data_flat = data.reshape(n_nodes * 8, d_dim)
    geo = torch.float64          # ray geometry always in float64 (as in the numba kernel)
    offset_t = _as_tensor(tree.offset, geo, device).reshape(-1).expand(3)
    inv_t = _as_tensor(tree.invradius, geo, device).reshape(-1).expand(3)
    o = _as_tensor(origins, geo, device).reshape(-1, 3)
    d = _as_tensor(dirs, geo, device).reshape(-1, 3)
    n_rays = o.shape[0]
    d = d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)
    bg = torch.tensor(opts.background, dtype=dtype, device=device)

    o_t = offset_t + inv_t * o
    d_t = inv_t * d
    eps_t = opts.step_eps / _norm_no_overflow(d_t)
    t0, t1 = box_intersect_torch(o_t, d_t)
    d_safe = torch.where(d_t == 0, torch.full_like(d_t, 1.0 / _BIG), d_t)
    inv_d = 1.0 / d_safe
    positive = d_t >= 0
    basis = ray_basis_torch(info, d, extra_data, opts).to(dtype)   # [N, B]
    n_b = info.basis_dim

    rgb_acc = torch.zeros(n_rays, 3, dtype=dtype, device=device)
    w_sum = torch.zeros(n_rays, dtype=dtype, device=device)
    wt_sum = torch.zeros(n_rays, dtype=dtype, device=device)
    t_final = torch.ones(n_rays, dtype=dtype, device=device)

    idx = torch.nonzero(t0 < t1).reshape(-1)
    t = t0[idx]
    trans = torch.ones(idx.shape[0], dtype=dtype, device=device)
    max_levels = MAX_DEPTH + 1          # cell depths 0..MAX_DEPTH (check_integrity enforces it)
    deepest, steps = 0, 0
    inf_t = torch.tensor(float("inf"), dtype=geo, device=device)
    while idx.numel() > 0:
        if steps >= max_steps(deepest):     # the shader's cap: no input marches forever
            t_final = t_final.index_copy(0, idx, trans)
            break
        steps += 1
        # Locate the leaf holding p(t + eps_t): batched descent from the root.
        q = o_t[idx] + (t + eps_t[idx])[:, None] * d_t[idx]
        qi = torch.clamp(q * _SCALE, 0.0, _SCALE - 1.0).to(torch.int64)  # trunc = floor (>= 0)
        cell, level = _locate_leaves(child_flat, qi, max_levels)
        deepest = max(deepest, int(level.max()))
        # Exit distance of the leaf's box (tree units -> world t through d_t).
        cell_shift = (QUANT_BITS - 1 - level)[:, None]
        lo = ((qi >> cell_shift) << cell_shift).to(geo) / _SCALE
        size = torch.pow(2.0, -(level + 1).to(geo))[:, None]
        bound = torch.where(positive[idx], lo + size, lo)
        t_exit = ((bound - o_t[idx]) * inv_d[idx]).amin(dim=-1)
        # Forced progress: at least one float64 ulp even where t + eps_t rounds back to t.
        t_next = torch.maximum(t + eps_t[idx], torch.nextafter(t, inf_t))
        t_end = torch.minimum(torch.maximum(t_exit, t_next), t1[idx])
        delta = (t_end - t).to(dtype)

        vals = data_flat[cell]                                      # [n, D]
        sigma = torch.relu(vals[:, -1])
        att = torch.exp(-sigma * delta)
        w = trans * (1.0 - att)
        if info.kind == KIND_RGBA:
            coef = vals[:, :3, None]
        else:
            coef = vals[:, :-1].reshape(-1, 3, n_b)
        colour = torch.sigmoid((coef * basis[idx][:, None, :]).sum(-1))  # [n, 3]
        rgb_acc = rgb_acc.index_add(0, idx, w[:, None] * colour)
        w_sum = w_sum.index_add(0, idx, w)
        wt_sum = wt_sum.index_add(0, idx, w * (0.5 * (t + t_end)).to(dtype))
        trans = trans * att

        done = (t_end >= t1[idx]) | (trans < opts.stop_thresh)
        if bool(done.any()):
            t_final = t_final.index_copy(0, idx[done], trans[done])
            keep = ~done
            idx, t, trans = idx[keep], t_end[keep], trans[keep]
        else:
            t = t_end

    rgb = rgb_acc + t_final[:, None] * bg
    depth = wt_sum / torch.clamp(w_sum, min=1e-10)
    alpha = 1.0 - t_final
    if opts.renormalize:                # svox's fast rule for the rays stopped early
        early = t_final < opts.stop_thresh
        rgb = torch.where(early[:, None], rgb_acc / (1.0 - t_final)[:, None], rgb)
        alpha = torch.where(early, torch.ones_like(alpha), alpha)
    return RenderOutput(rgb=rgb, depth=depth, alpha=alpha)
