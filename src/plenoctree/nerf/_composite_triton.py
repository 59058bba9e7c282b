"""Triton GPU kernels of op ``composite`` (:mod:`plenoctree.nerf.composite`): the numba
kernels' loops (:mod:`._composite_numba`) with one lane per ray, a block of rays per program,
stepping every lane's next sample together until the block's longest ray is done; float32
arithmetic (the numba kernels and the twin accumulate in float64: equal within float32
rounding).
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

__all__ = ["composite_backend"]

BLOCK = 128


@triton.jit
def _fwd_kernel(sig_ptr, col_ptr, t_ptr, off_ptr, out_ptr, step, third, n,
                DIST: tl.constexpr, BLOCK: tl.constexpr):
    r = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    valid = r < n
    i = tl.load(off_ptr + r, mask=valid, other=0)
    end = tl.load(off_ptr + r + 1, mask=valid, other=0)
    zero = tl.zeros([BLOCK], dtype=tl.float32)
    trans = zero + 1.0
    cr, cg, cb, w_sum, wt_sum, loss = zero, zero, zero, zero, zero, zero
    active = valid & (i < end)
    while tl.sum(active.to(tl.int32), axis=0) > 0:
        s = tl.load(sig_ptr + i, mask=active, other=0.0)
        ti = tl.load(t_ptr + i, mask=active, other=0.0)
        att = tl.exp(-s * step)
        w = trans * (1.0 - att)
        cr += w * tl.load(col_ptr + i * 3 + 0, mask=active, other=0.0)
        cg += w * tl.load(col_ptr + i * 3 + 1, mask=active, other=0.0)
        cb += w * tl.load(col_ptr + i * 3 + 2, mask=active, other=0.0)
        if DIST:
            loss += 2.0 * w * (ti * w_sum - wt_sum) + third * w * w
        w_sum += w
        wt_sum += w * ti
        trans = tl.where(active, trans * att, trans)
        i = tl.where(active, i + 1, i)
        active = active & (i < end)
    base = out_ptr + r.to(tl.int64) * 6
    tl.store(base + 0, cr, mask=valid)
    tl.store(base + 1, cg, mask=valid)
    tl.store(base + 2, cb, mask=valid)
    tl.store(base + 3, w_sum, mask=valid)
    tl.store(base + 4, wt_sum, mask=valid)
    tl.store(base + 5, loss, mask=valid)


@triton.jit
def _sample(sig_ptr, col_ptr, t_ptr, i, active, trans, step, gr, gg, gb, ga, gd):
    """One sample of each lane: ``(e^{-τ}, t, w, ∂L/∂w without the distortion's term)``."""
    att = tl.exp(-tl.load(sig_ptr + i, mask=active, other=0.0) * step)
    ti = tl.load(t_ptr + i, mask=active, other=0.0)
    w = trans * (1.0 - att)
    g = (gr * tl.load(col_ptr + i * 3 + 0, mask=active, other=0.0)
         + gg * tl.load(col_ptr + i * 3 + 1, mask=active, other=0.0)
         + gb * tl.load(col_ptr + i * 3 + 2, mask=active, other=0.0) + ga + gd * ti)
    return att, ti, w, g


@triton.jit
def _bwd_kernel(sig_ptr, col_ptr, t_ptr, off_ptr, gout_ptr, gsig_ptr, gcol_ptr, step, third, n,
                BLOCK: tl.constexpr):
    r = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    valid = r < n
    gbase = gout_ptr + r.to(tl.int64) * 6
    gr = tl.load(gbase + 0, mask=valid, other=0.0)
    gg = tl.load(gbase + 1, mask=valid, other=0.0)
    gb = tl.load(gbase + 2, mask=valid, other=0.0)
    ga = tl.load(gbase + 3, mask=valid, other=0.0)
    gd = tl.load(gbase + 4, mask=valid, other=0.0)
    gl = tl.load(gbase + 5, mask=valid, other=0.0)
    start = tl.load(off_ptr + r, mask=valid, other=0)
    end = tl.load(off_ptr + r + 1, mask=valid, other=0)
    zero = tl.zeros([BLOCK], dtype=tl.float32)
    # pass 1: the totals and G = Σ w ∂loss/∂w (the totals' terms cancel in G)
    trans, w_sum, wt_sum, big_g = zero + 1.0, zero, zero, zero
    i = start
    active = valid & (i < end)
    while tl.sum(active.to(tl.int32), axis=0) > 0:
        att, ti, w, g = _sample(sig_ptr, col_ptr, t_ptr, i, active, trans, step, gr, gg, gb,
                                ga, gd)
        big_g += w * (g + gl * (4.0 * (ti * w_sum - wt_sum) + 2.0 * third * w))
        w_sum += w
        wt_sum += w * ti
        trans = tl.where(active, trans * att, trans)
        i = tl.where(active, i + 1, i)
        active = active & (i < end)
    w_tot, wt_tot = w_sum, wt_sum
    # pass 2: the gradients
    trans, w_sum, wt_sum, done = zero + 1.0, zero, zero, zero
    i = start
    active = valid & (i < end)
    while tl.sum(active.to(tl.int32), axis=0) > 0:
        att, ti, w, g = _sample(sig_ptr, col_ptr, t_ptr, i, active, trans, step, gr, gg, gb,
                                ga, gd)
        g += gl * (2.0 * (2.0 * (ti * w_sum - wt_sum) + wt_tot - ti * w_tot) + 2.0 * third * w)
        done += w * g
        trans = tl.where(active, trans * att, trans)
        tl.store(gsig_ptr + i, step * (trans * g - (big_g - done)), mask=active)
        tl.store(gcol_ptr + i * 3 + 0, w * gr, mask=active)
        tl.store(gcol_ptr + i * 3 + 1, w * gg, mask=active)
        tl.store(gcol_ptr + i * 3 + 2, w * gb, mask=active)
        w_sum += w
        wt_sum += w * ti
        i = tl.where(active, i + 1, i)
        active = active & (i < end)


def _grid(n: int) -> tuple[int]:
    return (max(1, triton.cdiv(n, BLOCK)),)


def _forward(sigma, color, t, offsets, step: float, dist: bool) -> torch.Tensor:
    n = offsets.shape[0] - 1
    out = torch.empty((n, 6), dtype=torch.float32, device=sigma.device)
    _fwd_kernel[_grid(n)](sigma, color, t, offsets, out, float(step), float(step) / 3.0, n,
                          DIST=bool(dist), BLOCK=BLOCK)
    return out


def _backward(sigma, color, t, offsets, step: float, grad_out) -> tuple[torch.Tensor,
                                                                         torch.Tensor]:
    n = offsets.shape[0] - 1
    g_sigma = torch.zeros_like(sigma)
    g_color = torch.zeros_like(color)
    _bwd_kernel[_grid(n)](sigma, color, t, offsets, grad_out, g_sigma, g_color, float(step),
                          float(step) / 3.0, n, BLOCK=BLOCK)
    return g_sigma, g_color


#: Op ``composite``'s Triton backend: ``(forward, backward)`` for
#: :class:`plenoctree.nerf.composite._Composite`.
composite_backend = (_forward, _backward)
