"""Triton kernel of the visibility filter: maximum ray weight per grid cell, on the device.

The numba kernel's semantics (:mod:`._visibility_numba`, tested against the torch twin
:func:`plenoctree.convert.visibility._max_weights_torch`), one ray per lane: each ray (any
non-zero direction, normalised here) is clipped to the grid box from ``t = 0`` and walked cell
by cell with a 3-D DDA (Amanatides & Woo; ties step x before y before z); the segment of world
length δ in cell ``c`` has weight ``w = T (1 - exp(-σ_c δ))``, then ``T *= exp(-σ_c δ)``; a
ray stops once ``T < min_weight`` or when it leaves the box. All ray arithmetic is float64 on
the lanes, in the numba kernel's order, compiled without fused multiply-adds; σ is read as
float32 and widened. Only candidate cells (``index[c] >= 0``) record, by ``tl.atomic_max`` of
``w`` rounded to float32 into one row ``out [M]`` (rounding is monotone, so the maximum of the
rounded weights is the rounded maximum, as in the numba kernel's per-thread rows).

A program takes ``BLOCK`` rays and loops while any of its lanes is active; a lane moves one
cell per iteration, so ``3 R + 3`` iterations bound any ray through an ``R³`` grid.
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

__all__ = ["max_weights_triton", "geometry", "BLOCK"]

BLOCK = 128


@triton.jit
def _slab(o, d, lo, hi, t0, t1):
    """Clip ``[t0, t1]`` (float64 lanes) to the slab ``[lo, hi]`` of one axis."""
    flat = d == 0.0
    safe = tl.where(flat, 1.0, d)
    ta = (lo - o) / safe
    tb = (hi - o) / safe
    near = tl.maximum(t0, tl.minimum(ta, tb))
    far = tl.minimum(t1, tl.maximum(ta, tb))
    outside = (o < lo) | (o > hi)
    near = tl.where(flat, tl.where(outside, 1.0, t0), near)
    far = tl.where(flat, tl.where(outside, 0.0, t1), far)
    return near, far


@triton.jit
def _start(o, d, lo, cell, last, t0):
    """``(cell index int32, step -1/0/1, first crossing t, crossing spacing)`` of one axis
    (``last = R - 1``, float64)."""
    p = (o + t0 * d - lo) / cell
    up = d > 0.0
    down = d < 0.0
    c = tl.where(down, tl.ceil(p) - 1.0, tl.floor(p))
    c = tl.minimum(tl.maximum(c, 0.0), last).to(tl.int32)
    cf = c.to(tl.float64)
    safe = tl.where(up | down, d, 1.0)
    t_up = (lo + (cf + 1.0) * cell - o) / safe
    t_down = (lo + cf * cell - o) / safe
    t_next = tl.where(up, t_up, tl.where(down, t_down, 1e300))
    spacing = tl.where(up, cell / safe, tl.where(down, -cell / safe, 1e300))
    step = tl.where(up, 1, tl.where(down, -1, 0)).to(tl.int32)
    return c, step, t_next, spacing


@triton.jit
def _visibility_kernel(sigma_ptr, index_ptr, o_ptr, d_ptr, out_ptr, geom_ptr, n, o_stride,
                       res, max_steps, BLOCK: tl.constexpr):
    # float64 constants come from a table: Triton passes Python floats as float32
    lox = tl.load(geom_ptr + 0)
    loy = tl.load(geom_ptr + 1)
    loz = tl.load(geom_ptr + 2)
    cx = tl.load(geom_ptr + 3)
    cy = tl.load(geom_ptr + 4)
    cz = tl.load(geom_ptr + 5)
    min_weight = tl.load(geom_ptr + 6)
    res_f = tl.load(geom_ptr + 7)
    r = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    valid = r < n
    r64 = r.to(tl.int64)
    ob = r64 * o_stride
    ox = tl.load(o_ptr + ob + 0, mask=valid, other=0.0).to(tl.float64)
    oy = tl.load(o_ptr + ob + 1, mask=valid, other=0.0).to(tl.float64)
    oz = tl.load(o_ptr + ob + 2, mask=valid, other=0.0).to(tl.float64)
    dx = tl.load(d_ptr + r64 * 3 + 0, mask=valid, other=0.0).to(tl.float64)
    dy = tl.load(d_ptr + r64 * 3 + 1, mask=valid, other=0.0).to(tl.float64)
    dz = tl.load(d_ptr + r64 * 3 + 2, mask=valid, other=0.0).to(tl.float64)
    norm = tl.sqrt(dx * dx + dy * dy + dz * dz)
    ok = norm > 0.0                                     # false for 0 and NaN
    norm = tl.where(ok, norm, 1.0)
    dx = dx / norm
    dy = dy / norm
    dz = dz / norm
    t0 = tl.zeros([BLOCK], tl.float64)
    t1 = tl.zeros([BLOCK], tl.float64) + 1e300
    t0, t1 = _slab(ox, dx, lox, lox + cx * res_f, t0, t1)
    t0, t1 = _slab(oy, dy, loy, loy + cy * res_f, t0, t1)
    t0, t1 = _slab(oz, dz, loz, loz + cz * res_f, t0, t1)
    active = valid & ok & (t1 > t0)
    i, si, ti, di = _start(ox, dx, lox, cx, res_f - 1.0, t0)
    j, sj, tj, dj = _start(oy, dy, loy, cy, res_f - 1.0, t0)
    k, sk, tk, dk = _start(oz, dz, loz, cz, res_f - 1.0, t0)
    t = t0
    trans = tl.zeros([BLOCK], tl.float64) + 1.0
    steps = tl.zeros([BLOCK], tl.int32)
    while tl.sum(active.to(tl.int32), axis=0) > 0:
        # the axis whose boundary comes first (x before y before z on ties)
        ax0 = (ti <= tj) & (ti <= tk)
        ax1 = ~ax0 & (tj <= tk)
        ax2 = ~ax0 & ~ax1
        te = tl.where(ax0, ti, tl.where(ax1, tj, tk))
        te = tl.minimum(te, t1)
        delta = te - t
        seg = active & (delta > 0.0)
        cell = (i.to(tl.int64) * res + j) * res + k
        s = tl.load(sigma_ptr + cell, mask=seg, other=0.0).to(tl.float64)
        hit = seg & (s > 0.0)
        att = tl.exp(-s * delta)
        w = trans * (1.0 - att)
        col = tl.load(index_ptr + cell, mask=hit, other=-1)
        rec = hit & (col >= 0)
        tl.atomic_max(out_ptr + tl.where(rec, col, 0).to(tl.int64), w.to(tl.float32), mask=rec)
        trans = tl.where(hit, trans * att, trans)
        active = active & ~(hit & (trans < min_weight))
        t = tl.where(seg, te, t)
        active = active & ~(te >= t1)
        i = tl.where(active & ax0, i + si, i)
        j = tl.where(active & ax1, j + sj, j)
        k = tl.where(active & ax2, k + sk, k)
        ti = tl.where(active & ax0, ti + di, ti)
        tj = tl.where(active & ax1, tj + dj, tj)
        tk = tl.where(active & ax2, tk + dk, tk)
        inside = (i >= 0) & (i < res) & (j >= 0) & (j < res) & (k >= 0) & (k < res)
        steps += 1
        active = active & inside & (steps < max_steps)


def geometry(lo, cell, res: int, min_weight: float, device) -> torch.Tensor:
    """The kernel's float64 table ``[lo (3), cell (3), min_weight, R]`` on ``device``."""
    vals = [*(float(v) for v in lo), *(float(v) for v in cell), float(min_weight), float(res)]
    return torch.tensor(vals, dtype=torch.float64, device=device)


def max_weights_triton(sigma: torch.Tensor, index: torch.Tensor, geom: torch.Tensor,
                       origins: torch.Tensor, dirs: torch.Tensor, out: torch.Tensor) -> None:
    """Raise ``out`` in place to the maximum ray weight of each candidate cell (one launch,
    no read-back).

    Args:
        sigma: float32 ``[R, R, R]`` σ per cell (1 / world length), contiguous.
        index: int32 ``[R, R, R]``: column of ``out`` for candidate cells, -1 otherwise.
        geom: float64 ``[8]`` from :func:`geometry` (grid corner and cell sides in world
            units, ``min_weight``: stop a ray once its transmittance is below it, ``R``).
        origins: float32 ``[N, 3]``, or ``[3]`` (one origin shared by every ray: a pinhole
            view, read with stride 0). dirs: float32 ``[N, 3]`` (any non-zero length).
        out: float32 ``[M]`` (or ``[1, M]``) running maxima, contiguous.

    All tensors on one device: CUDA, or the CPU in Triton's interpreter (tests).
    """
    from .._triton import interpret_mode, require_triton

    require_triton(sigma.device, "visibility")
    n = dirs.shape[0]
    if n == 0:
        return
    res = int(sigma.shape[0])
    o_stride = 0 if origins.dim() == 1 else 3
    block = 1024 if interpret_mode() else BLOCK
    opts = {} if interpret_mode() else {"enable_fp_fusion": False}
    _visibility_kernel[(triton.cdiv(n, block),)](
        sigma, index, origins.contiguous(), dirs.contiguous(), out, geom, n, o_stride, res,
        3 * res + 3, BLOCK=block, **opts)
