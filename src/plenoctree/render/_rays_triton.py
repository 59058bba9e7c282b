"""Triton kernel of the march kernel's rays on the device, one launch (issue 47): pixels of
photos (the fine-tuning loop's tiles, ``batch_rays``) or of a camera alone (``render_image``'s
frame, ``camera_rays``) → camera rays (pinhole, NDC, NDC with the "any camera" clip: the numba
``_camera_ray``) → the march kernel's per-ray geometry
(:func:`plenoctree.render._triton_impl.prepare_rays`), the basis values
(:func:`plenoctree.render._torch_impl.ray_basis_torch`) and, for photos, the targets.

Float arguments of a Triton kernel are float32, and so are its float literals: the float64
inputs (tree box, ``step_eps``, the photos' unit) come in a small float64 tensor uploaded once
per tree (:func:`geometry_tensor`); the SH constants are float32-rounded literals, so a basis
value may differ from the twin's by one float32 ulp. Twins and tests: see
:mod:`plenoctree.optim._device_kernels`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
import triton
import triton.language as tl

from ..sh import SH_C0, SH_C1, SH_C2, SH_C3, SH_C4
from .options import KIND_RGBA, KIND_SG, KIND_SH

__all__ = ["GEO_COLS", "COL_OUTSIDE", "geometry_tensor", "batch_rays", "camera_rays"]


def _interp() -> bool:
    from .._triton import interpret_mode

    return interpret_mode()


GEO_COLS = 14
#: Column of the march kernel's geometry rows (unused by it) flagging a ray past the border.
COL_OUTSIDE = 12
# Triton kernels read only constexpr globals: the SH constants one by one (float32 literals)
_C0 = tl.constexpr(SH_C0)
_C1 = tl.constexpr(SH_C1)
_C2_0, _C2_1, _C2_2, _C2_3, _C2_4 = (tl.constexpr(c) for c in SH_C2)
_C3_0, _C3_1, _C3_2, _C3_3, _C3_4, _C3_5, _C3_6 = (tl.constexpr(c) for c in SH_C3)
(_C4_0, _C4_1, _C4_2, _C4_3, _C4_4, _C4_5, _C4_6, _C4_7,
 _C4_8) = (tl.constexpr(c) for c in SH_C4)


def geometry_tensor(offset: Any, invradius: Any, step_eps: float, device: torch.device
                    ) -> torch.Tensor:
    """float64 ``[8]`` on ``device``: ``offset (3), invradius (3), step_eps, 0`` (one upload
    per tree)."""
    g = np.zeros(8, np.float64)
    g[0:3] = np.broadcast_to(np.asarray(offset, np.float64).reshape(-1), (3,))
    g[3:6] = np.broadcast_to(np.asarray(invradius, np.float64).reshape(-1), (3,))
    g[6] = float(step_eps)
    return torch.from_numpy(g).to(device)


@triton.jit
def _put(basis_ptr, ray, m, col: tl.constexpr, val, lo, hi, B: tl.constexpr):
    keep = (col >= lo) & (col <= hi)
    tl.store(basis_ptr + ray * B + col, tl.where(keep, val, 0.0).to(basis_ptr.dtype.element_ty),
             mask=m)


@triton.jit
def _sh_basis(basis_ptr, ray, m, x, y, z, lo, hi, B: tl.constexpr, DEG: tl.constexpr):
    """Real SH up to degree ``DEG`` (``sh.eval_sh_bases``, svox signs) at unit ``(x, y, z)``."""
    _put(basis_ptr, ray, m, 0, x * 0.0 + _C0, lo, hi, B)
    if DEG >= 1:
        _put(basis_ptr, ray, m, 1, -_C1 * y, lo, hi, B)
        _put(basis_ptr, ray, m, 2, _C1 * z, lo, hi, B)
        _put(basis_ptr, ray, m, 3, -_C1 * x, lo, hi, B)
    if DEG >= 2:
        xx = x * x
        yy = y * y
        zz = z * z
        xy = x * y
        yz = y * z
        xz = x * z
        _put(basis_ptr, ray, m, 4, _C2_0 * xy, lo, hi, B)
        _put(basis_ptr, ray, m, 5, _C2_1 * yz, lo, hi, B)
        _put(basis_ptr, ray, m, 6, _C2_2 * (2.0 * zz - xx - yy), lo, hi, B)
        _put(basis_ptr, ray, m, 7, _C2_3 * xz, lo, hi, B)
        _put(basis_ptr, ray, m, 8, _C2_4 * (xx - yy), lo, hi, B)
        if DEG >= 3:
            _put(basis_ptr, ray, m, 9, _C3_0 * y * (3.0 * xx - yy), lo, hi, B)
            _put(basis_ptr, ray, m, 10, _C3_1 * xy * z, lo, hi, B)
            _put(basis_ptr, ray, m, 11, _C3_2 * y * (4.0 * zz - xx - yy), lo, hi, B)
            _put(basis_ptr, ray, m, 12, _C3_3 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy), lo, hi,
                 B)
            _put(basis_ptr, ray, m, 13, _C3_4 * x * (4.0 * zz - xx - yy), lo, hi, B)
            _put(basis_ptr, ray, m, 14, _C3_5 * z * (xx - yy), lo, hi, B)
            _put(basis_ptr, ray, m, 15, _C3_6 * x * (xx - 3.0 * yy), lo, hi, B)
        if DEG >= 4:
            _put(basis_ptr, ray, m, 16, _C4_0 * xy * (xx - yy), lo, hi, B)
            _put(basis_ptr, ray, m, 17, _C4_1 * yz * (3.0 * xx - yy), lo, hi, B)
            _put(basis_ptr, ray, m, 18, _C4_2 * xy * (7.0 * zz - 1.0), lo, hi, B)
            _put(basis_ptr, ray, m, 19, _C4_3 * yz * (7.0 * zz - 3.0), lo, hi, B)
            _put(basis_ptr, ray, m, 20, _C4_4 * (zz * (35.0 * zz - 30.0) + 3.0), lo, hi, B)
            _put(basis_ptr, ray, m, 21, _C4_5 * xz * (7.0 * zz - 3.0), lo, hi, B)
            _put(basis_ptr, ray, m, 22, _C4_6 * (xx - yy) * (7.0 * zz - 1.0), lo, hi, B)
            _put(basis_ptr, ray, m, 23, _C4_7 * xz * (xx - 3.0 * yy), lo, hi, B)
            _put(basis_ptr, ray, m, 24, _C4_8 * (xx * (xx - 3.0 * yy) - yy * (3.0 * xx - yy)),
                 lo, hi, B)


@triton.jit
def _camera_ray(cams_ptr, img, m, u, v):
    """The numba ``_camera_ray`` (pinhole, NDC, NDC with the "any camera" clip) per lane:
    float32 ``(ox, oy, oz, dx, dy, dz)``."""
    c = cams_ptr + img * 20
    kind = tl.load(c + 0, mask=m, other=1.0)
    a = (u.to(tl.float64) + 0.5 - tl.load(c + 3, mask=m, other=0.0)) / tl.load(c + 1, mask=m,
                                                                               other=1.0)
    b = -(v.to(tl.float64) + 0.5 - tl.load(c + 4, mask=m, other=0.0)) / tl.load(c + 2, mask=m,
                                                                                other=1.0)
    x = a * tl.load(c + 5, mask=m, other=0.0) + b * tl.load(c + 6, mask=m, other=0.0) \
        - tl.load(c + 7, mask=m, other=0.0)
    y = a * tl.load(c + 8, mask=m, other=0.0) + b * tl.load(c + 9, mask=m, other=0.0) \
        - tl.load(c + 10, mask=m, other=0.0)
    z = a * tl.load(c + 11, mask=m, other=0.0) + b * tl.load(c + 12, mask=m, other=0.0) \
        - tl.load(c + 13, mask=m, other=1.0)
    nrm = tl.sqrt(x * x + y * y + z * z)
    dx = (x / nrm).to(tl.float32)
    dy = (y / nrm).to(tl.float32)
    dz = (z / nrm).to(tl.float32)
    ox = tl.load(c + 14, mask=m, other=0.0).to(tl.float32)
    oy = tl.load(c + 15, mask=m, other=0.0).to(tl.float32)
    oz = tl.load(c + 16, mask=m, other=0.0).to(tl.float32)
    # NDC (kind 2; kind 3 with the clip rule), computed for every lane and selected
    fx = tl.load(c + 17, mask=m, other=1.0)
    fy = tl.load(c + 18, mask=m, other=1.0)
    near = tl.load(c + 19, mask=m, other=1.0)
    ndc = (kind == 2.0) | (kind == 3.0)
    clip = kind == 3.0
    # pinhole lanes get a harmless NDC input (no 0 / 0 in the branch they do not take)
    near = tl.where(ndc, near, 1.0)
    o_x, o_y = ox.to(tl.float64), oy.to(tl.float64)
    o_z = tl.where(ndc, oz.to(tl.float64), -2.0)
    e_x, e_y = dx.to(tl.float64), dy.to(tl.float64)
    e_z = tl.where(ndc, dz.to(tl.float64), -1.0)
    behind = clip & (o_z <= -near)
    away = clip & (~behind) & (~(e_z < -1e-12))
    t = -(near + o_z) / e_z
    qx, qy, qz = o_x + t * e_x, o_y + t * e_y, o_z + t * e_z
    rx, ry = qx / qz, qy / qz
    px = tl.where(behind, fx * o_x / o_z, fx * rx)
    py = tl.where(behind, fy * o_y / o_z, fy * ry)
    pz = tl.where(behind, 1.0 + 2.0 * near / o_z, 1.0 + 2.0 * near / qz)
    nx = tl.where(behind, fx * (e_x * o_z - o_x * e_z), fx * (e_x / e_z - rx))
    ny = tl.where(behind, fy * (e_y * o_z - o_y * e_z), fy * (e_y / e_z - ry))
    nz = tl.where(behind, -2.0 * near * e_z, -2.0 * near / qz)
    ok = (~away) & ((~behind) | (nx != 0.0) | (ny != 0.0) | (nz != 0.0))
    miss = clip & ~(ok & (tl.abs(px) <= 1.0e4) & (tl.abs(py) <= 1.0e4))
    nn = tl.sqrt(nx * nx + ny * ny + nz * nz)
    ox = tl.where(ndc, tl.where(miss, 0.0, px.to(tl.float32)), ox)
    oy = tl.where(ndc, tl.where(miss, 0.0, py.to(tl.float32)), oy)
    oz = tl.where(ndc, tl.where(miss, 1.0e4, pz.to(tl.float32)), oz)
    dx = tl.where(ndc, tl.where(miss, 0.0, (nx / nn).to(tl.float32)), dx)
    dy = tl.where(ndc, tl.where(miss, 0.0, (ny / nn).to(tl.float32)), dy)
    dz = tl.where(ndc, tl.where(miss, 1.0, (nz / nn).to(tl.float32)), dz)
    return ox, oy, oz, dx, dy, dz


@triton.jit
def _slab(o, d, lo_prev, hi_prev):
    """Narrow ``[lo, hi]`` by the slab ``0 <= o + t d <= 1`` of one axis (``box_intersect``)."""
    zero = d == 0.0
    inv = 1.0 / tl.where(zero, 1.0, d)
    ta = (0.0 - o) * inv
    tb = (1.0 - o) * inv
    inside = (o >= 0.0) & (o <= 1.0)
    lo = tl.where(zero, tl.where(inside, -1e30, 1e30), tl.minimum(ta, tb))
    hi = tl.where(zero, tl.where(inside, 1e30, -1e30), tl.maximum(ta, tb))
    return tl.maximum(lo_prev, lo), tl.minimum(hi_prev, hi)


@triton.jit
def _rays_kernel(tiles_ptr, cams_ptr, img_ptr, geom_ptr, unit_ptr, extra_ptr, geo_ptr,
                 basis_ptr, tgt_ptr, n_rays, base, k, width, height, ntx, nty, lo, hi,
                 CONTIG: tl.constexpr, U16: tl.constexpr, KIND: tl.constexpr,
                 DEG: tl.constexpr, B: tl.constexpr, BP: tl.constexpr, BLOCK: tl.constexpr,
                 TARGETS: tl.constexpr = True):
    pid = tl.program_id(0)
    j = pid.to(tl.int64) * BLOCK + tl.arange(0, BLOCK).to(tl.int64)
    m = j < n_rays
    kk = k * k
    jt = j // kk
    within = j - jt * kk
    if CONTIG:
        tile = base + jt
    else:
        tile = tl.load(tiles_ptr + jt, mask=m, other=0).to(tl.int64) + base
    per_img = nty * ntx
    img = tile // per_img
    rem = tile - img * per_img
    ty = rem // ntx
    v = ty * k + within // k
    u = (rem - ty * ntx) * k + within % k
    outside = (v >= height) | (u >= width)
    u = tl.minimum(u, width - 1)
    v = tl.minimum(v, height - 1)
    ox, oy, oz, dx, dy, dz = _camera_ray(cams_ptr, img, m, u, v)
    if TARGETS:                   # (a frame rendered from a camera alone has no photo)
        px = ((img * height + v) * width + u) * 3
        unit = tl.load(unit_ptr)
        for ch in tl.static_range(3):
            raw = tl.load(img_ptr + px + ch, mask=m, other=0)
            if U16:
                val = ((raw.to(tl.int32) & 0xFFFF).to(tl.float64) * unit).to(tl.float32)
            else:
                val = raw.to(tl.float32)
            tl.store(tgt_ptr + j * 3 + ch, val, mask=m)
    # per-ray geometry (render._triton_impl.prepare_rays)
    x, y, z = ox.to(tl.float64), oy.to(tl.float64), oz.to(tl.float64)
    ex, ey, ez = dx.to(tl.float64), dy.to(tl.float64), dz.to(tl.float64)
    n = tl.sqrt(ex * ex + ey * ey + ez * ez)
    ex, ey, ez = ex / n, ey / n, ez / n
    otx = tl.load(geom_ptr + 0) + tl.load(geom_ptr + 3) * x
    oty = tl.load(geom_ptr + 1) + tl.load(geom_ptr + 4) * y
    otz = tl.load(geom_ptr + 2) + tl.load(geom_ptr + 5) * z
    dtx = tl.load(geom_ptr + 3) * ex
    dty = tl.load(geom_ptr + 4) * ey
    dtz = tl.load(geom_ptr + 5) * ez
    eps_t = tl.load(geom_ptr + 6) / tl.sqrt(dtx * dtx + dty * dty + dtz * dtz)
    t0 = x * 0.0 - 1e30
    t1 = x * 0.0 + 1e30
    t0, t1 = _slab(otx, dtx, t0, t1)
    t0, t1 = _slab(oty, dty, t0, t1)
    t0, t1 = _slab(otz, dtz, t0, t1)
    t0 = tl.maximum(t0, 0.0)
    t0 = tl.where(outside, 1.0, t0)          # a pixel past the border: a ray that misses
    t1 = tl.where(outside, 0.0, t1)
    g = geo_ptr + j * 14
    tl.store(g + 0, otx, mask=m)
    tl.store(g + 1, oty, mask=m)
    tl.store(g + 2, otz, mask=m)
    tl.store(g + 3, dtx, mask=m)
    tl.store(g + 4, dty, mask=m)
    tl.store(g + 5, dtz, mask=m)
    tl.store(g + 6, 1.0 / tl.where(dtx == 0.0, 1e-30, dtx), mask=m)
    tl.store(g + 7, 1.0 / tl.where(dty == 0.0, 1e-30, dty), mask=m)
    tl.store(g + 8, 1.0 / tl.where(dtz == 0.0, 1e-30, dtz), mask=m)
    tl.store(g + 9, t0, mask=m)
    tl.store(g + 10, t1, mask=m)
    tl.store(g + 11, eps_t, mask=m)
    tl.store(g + 12, outside.to(tl.float64), mask=m)
    tl.store(g + 13, x * 0.0, mask=m)
    # basis values (render._torch_impl.ray_basis_torch)
    if KIND == 0:
        _sh_basis(basis_ptr, j, m, ex, ey, ez, lo, hi, B, DEG)
    elif KIND == 1:
        b = tl.arange(0, BP)
        bm = b < B
        lam = tl.load(extra_ptr + b * 4 + 0, mask=bm, other=0.0).to(tl.float64)
        mx = tl.load(extra_ptr + b * 4 + 1, mask=bm, other=0.0).to(tl.float64)
        my = tl.load(extra_ptr + b * 4 + 2, mask=bm, other=0.0).to(tl.float64)
        mz = tl.load(extra_ptr + b * 4 + 3, mask=bm, other=0.0).to(tl.float64)
        cos = ex[:, None] * mx[None, :] + ey[:, None] * my[None, :] + ez[:, None] * mz[None, :]
        val = tl.exp(lam[None, :] * (cos - 1.0)) / B
        keep = (b >= lo) & (b <= hi)
        val = tl.where(keep[None, :], val, 0.0)
        tl.store(basis_ptr + j[:, None] * B + b[None, :], val.to(basis_ptr.dtype.element_ty),
                 mask=m[:, None] & bm[None, :])
    else:
        _put(basis_ptr, j, m, 0, x * 0.0 + 1.0, lo, hi, B)


def batch_rays(tiles: torch.Tensor | None, n_tiles: int, base: int, k: int, views: Any,
               geom: torch.Tensor, info: Any, extra: torch.Tensor | None,
               basis_range: tuple[int, int], out: tuple[torch.Tensor, torch.Tensor,
                                                        torch.Tensor]) -> int:
    """One launch: the rays of ``n_tiles`` ``k × k`` tiles into ``out = (geo, basis, targets)``
    (rows ``0 … n_tiles k² - 1``); returns that number of rays.

    ``tiles`` int64 ``[n_tiles]`` on the device (tile numbers, plus ``base``), or None for the
    contiguous tiles ``base … base + n_tiles - 1`` (``k = 1``: flat pixels, a view's own).
    ``views``: a :class:`~plenoctree.optim._device_stepper.DeviceViews` (photos, packed
    cameras, unit); ``geom``: :func:`geometry_tensor`; ``info``: the tree's
    :class:`~plenoctree.render.options.FormatInfo`; ``extra`` SG ``[B, 4]`` on the device.
    ``geo [N, 14]`` float64 as :func:`~plenoctree.render._triton_impl.prepare_rays` (column
    :data:`COL_OUTSIDE` = 1 and a missing ray for pixels past the border), ``basis [N, B]``,
    ``targets [N, 3]`` float32."""
    geo, basis, tgt = out
    n = n_tiles * k * k
    if n == 0:
        return 0
    block = 256 if _interp() else 128
    b = info.basis_dim
    lo, hi = basis_range
    kind = {KIND_SH: 0, KIND_SG: 1, KIND_RGBA: 2}[info.kind]
    _rays_kernel[(triton.cdiv(n, block),)](
        geo if tiles is None else tiles, views.cams, views.images, geom, views.unit,
        extra if extra is not None else geom, geo, basis, tgt, n, int(base), int(k),
        views.width, views.height, -(-views.width // k), -(-views.height // k), int(lo),
        int(hi), CONTIG=tiles is None, U16=views.images.dtype == torch.int16, KIND=kind,
        DEG=max(info.sh_degree, 0), B=b, BP=max(triton.next_power_of_2(b), 2), BLOCK=block)
    return n


def camera_rays(cams: torch.Tensor, width: int, height: int, geom: torch.Tensor, info: Any,
                extra: torch.Tensor | None, basis_range: tuple[int, int],
                out: tuple[torch.Tensor, torch.Tensor]) -> None:
    """One launch: the rays of every pixel of the camera ``cams`` (float64 ``[1, 20]``,
    ``pack_cameras``; row-major) into ``out = (geo [H W, 14] float64, basis [H W, B])``, as
    :func:`batch_rays` makes a view's (no photo, no targets): what
    :func:`plenoctree.render.render_image` draws on the device."""
    geo, basis = out
    n = int(width) * int(height)
    if n == 0:
        return
    block = 256 if _interp() else 128
    b = info.basis_dim
    lo, hi = basis_range
    kind = {KIND_SH: 0, KIND_SG: 1, KIND_RGBA: 2}[info.kind]
    _rays_kernel[(triton.cdiv(n, block),)](
        geo, cams, cams, geom, geom, extra if extra is not None else geom, geo, basis, geo, n,
        0, 1, int(width), int(height), int(width), int(height), int(lo), int(hi),
        CONTIG=True, U16=False, KIND=kind, DEG=max(info.sh_degree, 0), B=b,
        BP=max(triton.next_power_of_2(b), 2), BLOCK=block, TARGETS=False)
