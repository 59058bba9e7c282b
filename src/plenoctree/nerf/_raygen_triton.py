"""Triton kernel of op ``ray_batch`` (:mod:`plenoctree.nerf.raygen`): the rays, targets,
backgrounds and box bounds of a training step in one launch, one ray per lane.

The same arithmetic as the numba kernel (:mod:`._raygen_numba`) and the twin's order: the rays
in float64 (its divisions and square roots correctly rounded), then rounded to float32; the
colours and the bounds in float32 (the reciprocal by ``div_rn``, as torch's). Compiled without
fused multiply-adds, as the march kernels.
"""

from __future__ import annotations

import triton
import triton.language as tl

__all__ = ["ray_batch_backend"]

BLOCK = 256


@triton.jit
def _pinhole(c2w_ptr, k_ptr, img, col, row, valid):
    """World origin and unit direction (float64) of pixel ``(col, row)`` of camera ``img``."""
    fx = tl.load(k_ptr + img * 4 + 0, mask=valid, other=1.0)
    fy = tl.load(k_ptr + img * 4 + 1, mask=valid, other=1.0)
    cx = tl.load(k_ptr + img * 4 + 2, mask=valid, other=0.0)
    cy = tl.load(k_ptr + img * 4 + 3, mask=valid, other=0.0)
    x = (col + 0.5 - cx) / fx
    y = -(row + 0.5 - cy) / fy
    m = c2w_ptr + img * 16
    dx = (tl.load(m + 0, mask=valid, other=0.0) * x + tl.load(m + 1, mask=valid, other=0.0) * y
          + tl.load(m + 2, mask=valid, other=0.0) * -1.0)
    dy = (tl.load(m + 4, mask=valid, other=0.0) * x + tl.load(m + 5, mask=valid, other=0.0) * y
          + tl.load(m + 6, mask=valid, other=0.0) * -1.0)
    dz = (tl.load(m + 8, mask=valid, other=0.0) * x + tl.load(m + 9, mask=valid, other=0.0) * y
          + tl.load(m + 10, mask=valid, other=1.0) * -1.0)
    norm = tl.sqrt(dx * dx + dy * dy + dz * dz)
    ox = tl.load(m + 3, mask=valid, other=0.0)
    oy = tl.load(m + 7, mask=valid, other=0.0)
    oz = tl.load(m + 11, mask=valid, other=0.0)
    return ox, oy, oz, dx / norm, dy / norm, dz / norm


@triton.jit
def _ndc(ox, oy, oz, dx, dy, dz, ax, ay, near):
    """NeRF's NDC ray (unit direction) of a world ray pointing down -z."""
    t = -(near + oz) / dz
    px = ox + t * dx
    py = oy + t * dy
    pz = oz + t * dz
    rx = px / pz
    ry = py / pz
    nx = ax * (dx / dz - rx)
    ny = ay * (dy / dz - ry)
    nz = (-2.0 * near) / pz
    norm = tl.sqrt(nx * nx + ny * ny + nz * nz)
    return ax * rx, ay * ry, 1.0 + (2.0 * near) / pz, nx / norm, ny / norm, nz / norm


@triton.jit
def _slab(o, d, box_ptr, c: tl.constexpr):
    """``(t_near, t_far)`` of axis ``c`` (float32), as ``sampling.ray_aabb``."""
    lo = tl.load(box_ptr + c)
    hi = tl.load(box_ptr + 3 + c)
    inv = tl.math.div_rn(tl.full(d.shape, 1.0, tl.float32), tl.where(d == 0, 1e-12, d))
    t0 = (lo - o) * inv
    t1 = (hi - o) * inv
    return tl.minimum(t0, t1), tl.maximum(t0, t1)


@triton.jit
def _colour(r64, p, c: tl.constexpr, u_ptr, img_ptr, alpha_ptr, bg_ptr, o_bg, o_t, valid,
            MODE: tl.constexpr):
    """Background and target of channel ``c`` (float32)."""
    rgb = tl.load(img_ptr + p * 3 + c, mask=valid, other=0.0)
    bg_data = tl.load(bg_ptr + c)
    if MODE == 0:
        bg = tl.zeros(rgb.shape, tl.float32) + bg_data
    else:
        bg = tl.load(u_ptr + r64 * 4 + 1 + c, mask=valid, other=0.0).to(tl.float32)
    if MODE == 1:
        oma = 1.0 - tl.load(alpha_ptr + p, mask=valid, other=1.0)
        rgb = rgb - oma * bg_data + oma * bg
    tl.store(o_bg + r64 * 3 + c, bg, mask=valid)
    tl.store(o_t + r64 * 3 + c, rgb, mask=valid)


@triton.jit
def _ray_batch_kernel(u_ptr, c2w_ptr, k_ptr, img_ptr, alpha_ptr, bg_ptr, const_ptr, box_ptr,
                      n, total, hw, width, o_o, o_d, o_t, o_bg, o_tmin, o_tmax,
                      MODE: tl.constexpr, NDC: tl.constexpr, BLOCK: tl.constexpr):
    r = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    valid = r < n
    r64 = r.to(tl.int64)
    u0 = tl.load(u_ptr + r64 * 4, mask=valid, other=0.0)
    p = tl.minimum((u0 * total.to(tl.float64)).to(tl.int64), total - 1)
    img = p // hw
    row = (p - img * hw) // width
    col = p - img * hw - row * width
    ox, oy, oz, dx, dy, dz = _pinhole(c2w_ptr, k_ptr, img, col.to(tl.float64),
                                      row.to(tl.float64), valid)
    if NDC:
        ax = tl.load(const_ptr + 0)
        ay = tl.load(const_ptr + 1)
        nn = tl.load(const_ptr + 2)
        ox, oy, oz, dx, dy, dz = _ndc(ox, oy, oz, dx, dy, dz, ax, ay, nn)
    ox, oy, oz = ox.to(tl.float32), oy.to(tl.float32), oz.to(tl.float32)
    dx, dy, dz = dx.to(tl.float32), dy.to(tl.float32), dz.to(tl.float32)
    tl.store(o_o + r64 * 3 + 0, ox, mask=valid)
    tl.store(o_o + r64 * 3 + 1, oy, mask=valid)
    tl.store(o_o + r64 * 3 + 2, oz, mask=valid)
    tl.store(o_d + r64 * 3 + 0, dx, mask=valid)
    tl.store(o_d + r64 * 3 + 1, dy, mask=valid)
    tl.store(o_d + r64 * 3 + 2, dz, mask=valid)
    a0, b0 = _slab(ox, dx, box_ptr, 0)
    a1, b1 = _slab(oy, dy, box_ptr, 1)
    a2, b2 = _slab(oz, dz, box_ptr, 2)
    near = tl.load(const_ptr + 3).to(tl.float32)
    far = tl.load(const_ptr + 4).to(tl.float32)
    t_near = tl.maximum(tl.maximum(a0, a1), a2)
    t_far = tl.minimum(tl.minimum(b0, b1), b2)
    tl.store(o_tmin + r64, tl.maximum(t_near, near), mask=valid)
    tl.store(o_tmax + r64, tl.minimum(t_far, far), mask=valid)
    for c in tl.static_range(3):
        _colour(r64, p, c, u_ptr, img_ptr, alpha_ptr, bg_ptr, o_bg, o_t, valid, MODE)


def ray_batch_backend(source, u, bbox):
    """Op ``ray_batch`` of :mod:`plenoctree.backend` (tensors on CUDA, or the CPU in the
    interpreter): :func:`~plenoctree.nerf.raygen.ray_batch` in one launch, 6 allocations."""
    from .._triton import interpret_mode, require_triton
    from .raygen import _check_kernel, empty_rays

    dev = u.device
    require_triton(dev, "ray_batch")
    _check_kernel(source, "triton")
    n = u.shape[0]
    out = empty_rays(n, dev)
    c2w, intr = source.tables
    alphas = source.alphas if source.alphas is not None else source.images
    block = 1024 if interpret_mode() else BLOCK
    opts = {} if interpret_mode() else {"enable_fp_fusion": False}
    hw = source.h * source.w
    _ray_batch_kernel[(triton.cdiv(max(n, 1), block),)](
        u, c2w, intr, source.images, alphas, source.bg, source.constants, bbox, n,
        source.n * hw, hw, source.w, out.origins, out.dirs, out.target, out.background,
        out.t_min, out.t_max, MODE=source.background_mode, NDC=bool(source.cameras.ndc),
        BLOCK=block, **opts)
    return out
