"""Triton kernels of the device-resident fine-tuning step (issue 47): one launch each.

A fine-tuning step on CUDA is five launches on buffers allocated once:
:func:`plenoctree.render._rays_triton.batch_rays` (tiles → rays → the march kernel's per-ray
geometry, basis values and targets; in render since render_image uses it too), the march
kernel's forward (``render/_triton_impl.py``), :func:`loss` (squared error into the step's
figures row, ``dL/dC``), the march kernel's backward (gradient scattered into a persistent
buffer) and :func:`update` (the lazy optimiser, which also clears the gradient rows it read).
No value is read back and no shape depends on the data.

Twins (``optim/_device_twins.py``): ``batch_rays`` = :func:`batch_pixels_torch` +
:func:`camera_rays_torch` + :func:`pixel_targets_torch` +
:func:`plenoctree.render._triton_impl.prepare_rays` + :func:`ray_basis_torch
<plenoctree.render._torch_impl.ray_basis_torch>`; ``loss`` = :func:`loss_torch`; ``update`` =
:func:`update_torch`. Tests: ``tests/test_finetune_device.py`` (Triton's interpreter on CPU).

Float arguments of a Triton kernel are float32: the float64 inputs of the rays come in a
small float64 tensor uploaded once per tree (``_rays_triton.geometry_tensor``).
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

from ._rules import FIG_BAD, FIG_RAYS, FIG_ROWS, FIG_SSE, N_FIGS

__all__ = ["loss", "update"]


def _interp() -> bool:
    from .._triton import interpret_mode

    return interpret_mode()


@triton.jit
def _loss_kernel(rgb_ptr, tgt_ptr, geo_ptr, grad_ptr, figs_ptr, slot, n_rays, scale2,
                 GRAD: tl.constexpr, BLOCK: tl.constexpr):
    pid = tl.program_id(0)
    ray = pid.to(tl.int64) * BLOCK + tl.arange(0, BLOCK).to(tl.int64)
    m = ray < n_rays
    inside = m & (tl.load(geo_ptr + ray * 14 + 12, mask=m, other=1.0) == 0.0)
    acc = tl.zeros([BLOCK], dtype=tl.float64)
    for ch in tl.static_range(3):
        c = tl.load(rgb_ptr + ray * 3 + ch, mask=m, other=0.0)
        t = tl.load(tgt_ptr + ray * 3 + ch, mask=m, other=0.0)
        e = tl.where(inside, c - t, 0.0)
        if GRAD:
            tl.store(grad_ptr + ray * 3 + ch, e * scale2, mask=m)
        acc += (e * e).to(tl.float64)
    row = figs_ptr + slot * 4
    tl.atomic_add(row + 0, tl.sum(acc, axis=0))
    tl.atomic_add(row + 1, tl.sum(inside.to(tl.float64), axis=0))


def loss(rgb: torch.Tensor, targets: torch.Tensor, geo: torch.Tensor, n: int, scale: float,
         figs: torch.Tensor, slot: int, grad: torch.Tensor | None) -> None:
    """One launch: ``Σ (C - C*)²`` of rays ``0 … n-1`` inside the images (float32 squares
    summed in float64) and their number added to row ``slot`` of ``figs`` (float64
    ``[S, 4]``, the figures buffer); with ``grad`` (float32 ``[≥ n, 3]``) writes ``dL/dC = 2 · scale (C - C*)``
    (0 past the border)."""
    if n == 0:
        return
    block = 1024 if _interp() else 256
    _loss_kernel[(triton.cdiv(n, block),)](rgb, targets, geo, grad if grad is not None else rgb,
                                           figs, int(slot), n, 2.0 * float(scale),
                                           GRAD=grad is not None, BLOCK=block)


@triton.jit
def _update_kernel(p_ptr, g_ptr, m1_ptr, m2_ptr, figs_ptr, slot, n_rows, lr, lr_sig, b1, one_b1,
                   b2, one_b2, bc1, bc2, eps, OPT: tl.constexpr, D: tl.constexpr,
                   DP: tl.constexpr, ROWS: tl.constexpr):
    pid = tl.program_id(0)
    r = pid.to(tl.int64) * ROWS + tl.arange(0, ROWS).to(tl.int64)
    c = tl.arange(0, DP)
    mm = (r < n_rows)[:, None] & (c < D)[None, :]
    off = r[:, None] * D + c[None, :]
    g = tl.load(g_ptr + off, mask=mm, other=0.0)
    touched = tl.max((g != 0.0).to(tl.int32), axis=1) > 0          # NaN counts as touched
    tm = mm & touched[:, None]
    p = tl.load(p_ptr + off, mask=tm, other=0.0)
    lrv = tl.where(c == D - 1, lr_sig, lr)[None, :]
    if OPT == 0:
        new = p - lrv * g
    elif OPT == 1:
        m1 = tl.load(m1_ptr + off, mask=tm, other=0.0)
        m2 = tl.load(m2_ptr + off, mask=tm, other=0.0)
        m1 = m1 * b1 + one_b1 * g
        m2 = m2 * b2 + one_b2 * g * g
        new = p - lrv * (m1 / bc1) / (tl.sqrt_rn(m2 / bc2) + eps)
        tl.store(m1_ptr + off, m1, mask=tm)
        tl.store(m2_ptr + off, m2, mask=tm)
    else:
        m2 = tl.load(m2_ptr + off, mask=tm, other=0.0)
        m2 = m2 * b2 + one_b2 * g * g
        new = p - lrv * g / (tl.sqrt_rn(m2) + eps)
        tl.store(m2_ptr + off, m2, mask=tm)
    bad = tm & ((new - new) != 0.0)                                 # inf - inf, NaN: NaN
    new = tl.where((c == D - 1)[None, :] & (new < 0.0), 0.0, new)   # σ ≥ 0 (NaN stays)
    tl.store(p_ptr + off, new, mask=tm)
    tl.store(g_ptr + off, tl.zeros([ROWS, DP], dtype=tl.float32), mask=tm)   # ready for the next
    row = figs_ptr + slot * 4
    tl.atomic_add(row + 2, tl.sum(tl.sum(bad.to(tl.float64), axis=1), axis=0))
    tl.atomic_add(row + 3, tl.sum(touched.to(tl.float64), axis=0))


def update(p: torch.Tensor, g: torch.Tensor, m1: torch.Tensor | None, m2: torch.Tensor | None,
           opt: int, lr: float, lr_sigma: float, hyper: tuple[float, float, float, float, float],
           figs: torch.Tensor, slot: int) -> None:
    """One launch: :func:`~plenoctree.optim._device_twins.update_torch` on ``p, g`` float32
    ``[n, D]`` (contiguous), which also zeroes the gradient rows it updated (the buffer is
    all zero again for the next backward); its figures go to row ``slot`` of ``figs``."""
    b1, b2, bc1, bc2, eps = hyper
    n, d = p.shape
    rows = 256 if _interp() else 32
    dummy = p
    _update_kernel[(triton.cdiv(max(n, 1), rows),)](
        p, g, m1 if m1 is not None else dummy, m2 if m2 is not None else dummy, figs, int(slot), n,
        float(lr), float(lr_sigma), float(b1), float(1 - b1), float(b2), float(1 - b2),
        float(bc1), float(bc2), float(eps), OPT=int(opt), D=d,
        DP=max(triton.next_power_of_2(d), 2), ROWS=rows)


assert (FIG_SSE, FIG_RAYS, FIG_BAD, FIG_ROWS, N_FIGS) == (0, 1, 2, 3, 4), "kernels hard-code them"
