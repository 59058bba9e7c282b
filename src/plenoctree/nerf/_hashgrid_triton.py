"""Triton GPU kernels of the multiresolution grid encoding (forward and table gradient).

Same numbers as the torch twin ``encoding._hashgrid_encode_torch`` (the spec) and the numba
kernels: per level ``l`` of resolution ``r``, ``p = x r``, ``i = clamp(floor(p), 0, r - 1)``,
``f = p - i``; the 8 corners ``i + c`` are looked up densely (``ix + iy (r+1) + iz (r+1)^2``)
or hashed (``(ix ^ iy P1 ^ iz P2) & (size - 1)``) in the level's rows of the table and mixed
with trilinear weights ``w = w_x w_y w_z``. The kernel maps the world points to the unit
cube itself (``clamp((p - lo) / (hi - lo), 0, 1)`` in float32 with a correctly rounded
division, the encoding's ``normalize``: six torch ops a call fewer). One program encodes
``BLOCK`` points over all levels; the backward scatters ``w g`` into the table gradient with
atomic adds (the points are not learnable, as in the numba kernel).
"""

from __future__ import annotations

import numpy as np
import torch
import triton
import triton.language as tl

from .encoding import _P1, _P2

__all__ = ["hashgrid_backend", "HashGridTriton"]

BLOCK = 128


@triton.jit
def _unit(x_ptr, box_ptr, r64, valid, a: tl.constexpr):
    """Axis ``a`` of world points ``x_ptr [N, 3]`` in the unit cube of ``box_ptr [2, 3]``."""
    lo = tl.load(box_ptr + a)
    ext = tl.load(box_ptr + 3 + a) - lo
    p = tl.load(x_ptr + r64 * 3 + a, mask=valid, other=0.0).to(tl.float32)
    return tl.minimum(tl.maximum(tl.math.div_rn(p - lo, ext), 0.0), 1.0)


@triton.jit
def _hashgrid_kernel(x_ptr, box_ptr, table_ptr, res_ptr, off_ptr, hashed_ptr, out_ptr, grad_ptr,
                     gtable_ptr, n, n_levels, p1, p2,
                     F: tl.constexpr, FP: tl.constexpr, BACKWARD: tl.constexpr,
                     BLOCK: tl.constexpr):
    pid = tl.program_id(0)
    row = pid * BLOCK + tl.arange(0, BLOCK)
    valid = row < n
    r64 = row.to(tl.int64)
    x = _unit(x_ptr, box_ptr, r64, valid, 0)
    y = _unit(x_ptr, box_ptr, r64, valid, 1)
    z = _unit(x_ptr, box_ptr, r64, valid, 2)
    fi = tl.arange(0, FP)
    fm = fi < F
    m2 = valid[:, None] & fm[None, :]
    lf = n_levels * F
    for lev in range(n_levels):
        r = tl.load(res_ptr + lev)
        off = tl.load(off_ptr + lev)
        size = tl.load(off_ptr + lev + 1) - off
        hashed = tl.load(hashed_ptr + lev) != 0
        rf = r.to(tl.float32)
        px = x * rf
        py = y * rf
        pz = z * rf
        ix = tl.minimum(tl.maximum(tl.floor(px), 0.0), rf - 1.0)
        iy = tl.minimum(tl.maximum(tl.floor(py), 0.0), rf - 1.0)
        iz = tl.minimum(tl.maximum(tl.floor(pz), 0.0), rf - 1.0)
        fx = px - ix
        fy = py - iy
        fz = pz - iz
        jx = ix.to(tl.int64)
        jy = iy.to(tl.int64)
        jz = iz.to(tl.int64)
        r1 = r + 1
        if BACKWARD:
            g = tl.load(grad_ptr + r64[:, None] * lf + lev * F + fi[None, :], mask=m2, other=0.0)
        else:
            acc = tl.zeros([BLOCK, FP], dtype=tl.float32)
        for c in tl.static_range(8):
            cx = jx + (c & 1)
            cy = jy + ((c >> 1) & 1)
            cz = jz + ((c >> 2) & 1)
            wx = fx if (c & 1) else 1.0 - fx
            wy = fy if ((c >> 1) & 1) else 1.0 - fy
            wz = fz if ((c >> 2) & 1) else 1.0 - fz
            w = wx * wy * wz
            hidx = (cx ^ (cy * p1) ^ (cz * p2)) & (size - 1)
            didx = cx + cy * r1 + cz * r1 * r1
            idx = off + tl.where(hashed, hidx, didx)
            ptrs = idx[:, None] * F + fi[None, :]
            if BACKWARD:
                tl.atomic_add(gtable_ptr + ptrs, w[:, None] * g, mask=m2)
            else:
                acc += w[:, None] * tl.load(table_ptr + ptrs, mask=m2, other=0.0)
        if not BACKWARD:
            tl.store(out_ptr + r64[:, None] * lf + lev * F + fi[None, :], acc, mask=m2)


_LAYOUTS: dict = {}


def _layout(res: np.ndarray, offsets: np.ndarray, hashed: np.ndarray, device: torch.device):
    """The level layout as device tensors, uploaded once per layout and device (each upload
    is a host round trip; the trainer encodes ~10 times a step). Keyed by the arrays' contents
    (a few dozen integers)."""
    key = (np.asarray(res).tobytes(), np.asarray(offsets).tobytes(),
           np.asarray(hashed).tobytes(), str(device))
    out = _LAYOUTS.get(key)
    if out is None:
        out = _LAYOUTS[key] = (torch.as_tensor(np.asarray(res, np.int64), device=device),
                               torch.as_tensor(np.asarray(offsets, np.int64), device=device),
                               torch.as_tensor(np.asarray(hashed, np.int32), device=device))
    return out


def _launch(x, box, table, layout, n_feat, grad=None, gtable=None, out=None):
    from .._triton import interpret_mode

    n = x.shape[0]
    block = 1024 if interpret_mode() else BLOCK
    res_t, off_t, hashed_t = layout
    fp = max(triton.next_power_of_2(n_feat), 2)
    dummy = table
    _hashgrid_kernel[(triton.cdiv(max(n, 1), block),)](
        x, box, table, res_t, off_t, hashed_t, out if out is not None else dummy,
        grad if grad is not None else dummy, gtable if gtable is not None else dummy,
        n, res_t.shape[0], _P1, _P2, F=n_feat, FP=fp, BACKWARD=grad is not None, BLOCK=block)


class HashGridTriton(torch.autograd.Function):
    """``forward(ctx, x [N, 3] world, box [2, 3] float32, table [T, F], res, offsets, hashed,
    in_place)``.

    ``in_place`` as in the numba Function: the backward adds straight into ``table.grad``.
    """

    @staticmethod
    def forward(ctx, x, box, table, res, offsets, hashed, in_place):
        x = x.detach().contiguous()
        tab = table.detach().contiguous()
        layout = _layout(res, offsets, hashed, x.device)
        n_feat = tab.shape[1]
        out = torch.empty((x.shape[0], len(res) * n_feat), dtype=torch.float32, device=x.device)
        if x.shape[0]:
            _launch(x, box, tab, layout, n_feat, out=out)
        ctx.save_for_backward(x, box)
        ctx.layout, ctx.tshape = layout, tab.shape
        ctx.table = table if in_place else None
        return out

    @staticmethod
    def backward(ctx, grad_out):
        x, box = ctx.saved_tensors
        table = ctx.table
        g = grad_out.float().contiguous()
        if table is not None:
            if table.grad is None:
                table.grad = torch.zeros(ctx.tshape, dtype=torch.float32, device=x.device)
            if x.shape[0]:
                _launch(x, box, table.grad, ctx.layout, ctx.tshape[1], grad=g,
                        gtable=table.grad)
            return None, None, None, None, None, None, None
        grad_table = torch.zeros(ctx.tshape, dtype=torch.float32, device=x.device)
        if x.shape[0]:
            _launch(x, box, grad_table, ctx.layout, ctx.tshape[1], grad=g, gtable=grad_table)
        return None, None, grad_table, None, None, None, None


def hashgrid_backend(enc, x: torch.Tensor) -> torch.Tensor:
    """Op ``hashgrid`` of :mod:`plenoctree.backend`: ``x [N, 3]`` world points (float32 or
    float64) -> ``[N, L*F]`` over ``enc.bbox``."""
    from .._triton import require_triton

    require_triton(x.device, "hash grid")
    return HashGridTriton.apply(x, enc.bbox, enc.table, enc.res, enc.offsets, enc.hashed,
                                enc.grad_in_place and torch.is_grad_enabled())
