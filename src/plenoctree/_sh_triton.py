"""Triton GPU kernel for NeRF-SH colours: ``rgb = sigmoid(Σ_b k_b Y_b(d))`` and its gradient
w.r.t. the coefficients, one launch each way (the torch twin,
:func:`plenoctree.nerf.model._sh_colors_torch`, takes ~55 ops forward and backward at SH
degree 3: every basis function is a few elementwise ops), and the renderer's per-ray basis
(:func:`sh_basis`). A leaf module beside :mod:`plenoctree.sh`: the NeRF-SH and the renderer
both use it.

Same maths as the numba kernels (:mod:`plenoctree.nerf._shcolor_numba`): the basis in float32 in the same
expression order, the backward pass recomputes it from the directions instead of keeping
``[M, B]`` of it.
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

from .sh import SH_C0, SH_C1, SH_C2, SH_C3, SH_C4

__all__ = ["sh_colors_backend", "sh_basis"]

BLOCK = 128


@triton.jit
def _put(out, b, k: tl.constexpr, val):
    return tl.where(b == k, val, out)


@triton.jit
def _basis(x, y, z, b, c0, c1, c20, c21, c22, c23, c24, c30, c31, c32, c33, c34, c35, c36,
           c40, c41, c42, c43, c44, c45, c46, c47, c48, DEG: tl.constexpr):
    """``[BLOCK, BP]`` SH basis of unit directions ``x, y, z [BLOCK, 1]`` at columns ``b [1,
    BP]`` (0 past the degree's ``(DEG + 1)²``)."""
    out = tl.where(b == 0, c0, 0.0) + x * 0.0
    if DEG >= 1:
        out = _put(out, b, 1, -c1 * y)
        out = _put(out, b, 2, c1 * z)
        out = _put(out, b, 3, -c1 * x)
    if DEG >= 2:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        out = _put(out, b, 4, c20 * xy)
        out = _put(out, b, 5, c21 * yz)
        out = _put(out, b, 6, c22 * (2.0 * zz - xx - yy))
        out = _put(out, b, 7, c23 * xz)
        out = _put(out, b, 8, c24 * (xx - yy))
        if DEG >= 3:
            out = _put(out, b, 9, c30 * y * (3.0 * xx - yy))
            out = _put(out, b, 10, c31 * xy * z)
            out = _put(out, b, 11, c32 * y * (4.0 * zz - xx - yy))
            out = _put(out, b, 12, c33 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy))
            out = _put(out, b, 13, c34 * x * (4.0 * zz - xx - yy))
            out = _put(out, b, 14, c35 * z * (xx - yy))
            out = _put(out, b, 15, c36 * x * (xx - 3.0 * yy))
        if DEG >= 4:
            out = _put(out, b, 16, c40 * xy * (xx - yy))
            out = _put(out, b, 17, c41 * yz * (3.0 * xx - yy))
            out = _put(out, b, 18, c42 * xy * (7.0 * zz - 1.0))
            out = _put(out, b, 19, c43 * yz * (7.0 * zz - 3.0))
            out = _put(out, b, 20, c44 * (zz * (35.0 * zz - 30.0) + 3.0))
            out = _put(out, b, 21, c45 * xz * (7.0 * zz - 3.0))
            out = _put(out, b, 22, c46 * (xx - yy) * (7.0 * zz - 1.0))
            out = _put(out, b, 23, c47 * xz * (xx - 3.0 * yy))
            out = _put(out, b, 24, c48 * (xx * (xx - 3.0 * yy) - yy * (3.0 * xx - yy)))
    return out


@triton.jit
def _row_basis(dir_ptr, m64, valid, b, c0, c1, c20, c21, c22, c23, c24, c30, c31, c32, c33,
               c34, c35, c36, c40, c41, c42, c43, c44, c45, c46, c47, c48, DEG: tl.constexpr):
    """``[BLOCK, BP]`` basis of the unit directions in rows ``m64`` of ``dir_ptr [N, 3]``."""
    x = tl.load(dir_ptr + m64 * 3 + 0, mask=valid, other=0.0).to(tl.float32)[:, None]
    y = tl.load(dir_ptr + m64 * 3 + 1, mask=valid, other=0.0).to(tl.float32)[:, None]
    z = tl.load(dir_ptr + m64 * 3 + 2, mask=valid, other=0.0).to(tl.float32)[:, None]
    return _basis(x, y, z, b, c0, c1, c20, c21, c22, c23, c24, c30, c31, c32, c33, c34, c35,
                  c36, c40, c41, c42, c43, c44, c45, c46, c47, c48, DEG)


@triton.jit
def _shcolor_kernel(coeff_ptr, dir_ptr, rgb_ptr, grad_ptr, gcoeff_ptr, n,
                    c0, c1, c20, c21, c22, c23, c24, c30, c31, c32, c33, c34, c35, c36,
                    c40, c41, c42, c43, c44, c45, c46, c47, c48,
                    DEG: tl.constexpr, B: tl.constexpr, BP: tl.constexpr,
                    BACKWARD: tl.constexpr, BLOCK: tl.constexpr):
    pid = tl.program_id(0)
    m = pid * BLOCK + tl.arange(0, BLOCK)
    valid = m < n
    m64 = m.to(tl.int64)
    b = tl.arange(0, BP)[None, :]
    basis = _row_basis(dir_ptr, m64, valid, b, c0, c1, c20, c21, c22, c23, c24, c30, c31, c32,
                       c33, c34, c35, c36, c40, c41, c42, c43, c44, c45, c46, c47, c48, DEG)
    m2 = valid[:, None] & (b < B)
    for c in tl.static_range(3):
        ptr = m64[:, None] * (3 * B) + c * B + b
        if BACKWARD:
            s = tl.load(rgb_ptr + m64 * 3 + c, mask=valid, other=0.0)
            g = tl.load(grad_ptr + m64 * 3 + c, mask=valid, other=0.0).to(tl.float32)
            g = g * s * (1.0 - s)
            tl.store(gcoeff_ptr + ptr, g[:, None] * basis, mask=m2)
        else:
            k = tl.load(coeff_ptr + ptr, mask=m2, other=0.0).to(tl.float32)
            acc = tl.sum(k * basis, axis=1)
            tl.store(rgb_ptr + m64 * 3 + c, 1.0 / (1.0 + tl.exp(-acc)), mask=valid)


_CONSTS = (SH_C0, SH_C1, *SH_C2, *SH_C3, *SH_C4)


def _launch(coeffs, dirs, degree: int, rgb, grad=None, gcoeffs=None) -> None:
    from ._triton import interpret_mode

    n = dirs.shape[0]
    if n == 0:
        return
    nb = (degree + 1) ** 2
    block = 1024 if interpret_mode() else BLOCK
    dummy = rgb
    _shcolor_kernel[(triton.cdiv(n, block),)](
        coeffs, dirs, rgb, dummy if grad is None else grad,
        dummy if gcoeffs is None else gcoeffs, n, *map(float, _CONSTS),
        DEG=int(degree), B=nb, BP=max(triton.next_power_of_2(nb), 2),
        BACKWARD=grad is not None, BLOCK=block)


class _SHColorsTriton(torch.autograd.Function):
    """Fused Triton SH colours; gradient w.r.t. the coefficients only (as the numba path)."""

    @staticmethod
    def forward(ctx, coeffs, dirs, degree):
        d = dirs.detach().contiguous()
        rgb = torch.empty((d.shape[0], 3), dtype=torch.float32, device=d.device)
        _launch(coeffs.detach().contiguous(), d, degree, rgb)
        ctx.save_for_backward(rgb, d)
        ctx.degree, ctx.in_dtype = degree, coeffs.dtype
        return rgb

    @staticmethod
    def backward(ctx, grad_rgb):
        rgb, d = ctx.saved_tensors
        nb = (ctx.degree + 1) ** 2
        grad = torch.empty((rgb.shape[0], 3 * nb), dtype=torch.float32, device=rgb.device)
        _launch(rgb, d, ctx.degree, rgb, grad_rgb.contiguous(), grad)
        return grad.to(ctx.in_dtype), None, None


def sh_colors_backend(coeffs: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """Op ``sh_colors`` of :mod:`plenoctree.backend` (CUDA tensors, or the CPU in the
    interpreter): ``rgb [N, 3]`` float32 from ``coeffs [N, 3·(degree+1)²]`` and unit
    ``dirs [N, 3]``."""
    from ._triton import require_triton

    require_triton(coeffs.device, "sh_colors")
    return _SHColorsTriton.apply(coeffs, dirs, int(degree))


@triton.jit
def _basis_kernel(dir_ptr, out_ptr, n, lo, hi,
                  c0, c1, c20, c21, c22, c23, c24, c30, c31, c32, c33, c34, c35, c36,
                  c40, c41, c42, c43, c44, c45, c46, c47, c48,
                  DEG: tl.constexpr, B: tl.constexpr, BP: tl.constexpr, BLOCK: tl.constexpr):
    pid = tl.program_id(0)
    m = pid * BLOCK + tl.arange(0, BLOCK)
    valid = m < n
    m64 = m.to(tl.int64)
    b = tl.arange(0, BP)[None, :]
    basis = _row_basis(dir_ptr, m64, valid, b, c0, c1, c20, c21, c22, c23, c24, c30, c31, c32,
                       c33, c34, c35, c36, c40, c41, c42, c43, c44, c45, c46, c47, c48, DEG)
    basis = tl.where((b >= lo) & (b <= hi), basis, 0.0)
    tl.store(out_ptr + m64[:, None] * B + b, basis, mask=valid[:, None] & (b < B))


def sh_basis(dirs: torch.Tensor, degree: int, band: tuple[int, int]) -> torch.Tensor:
    """float32 ``[N, (degree+1)²]`` SH basis of unit ``dirs [N, 3]`` (any float dtype), zero
    outside the basis indices ``band = (lo, hi)`` (the renderer's ``basis_range``): the
    renderer's per-ray basis in one launch (the twin: :func:`plenoctree.sh.eval_sh_bases`)."""
    from ._triton import interpret_mode

    d = dirs.contiguous()
    n, nb = d.shape[0], (degree + 1) ** 2
    out = torch.empty((n, nb), dtype=torch.float32, device=d.device)
    if n:
        block = 1024 if interpret_mode() else BLOCK
        _basis_kernel[(triton.cdiv(n, block),)](
            d, out, n, int(band[0]), int(band[1]), *map(float, _CONSTS), DEG=int(degree),
            B=nb, BP=max(triton.next_power_of_2(nb), 2), BLOCK=block)
    return out
