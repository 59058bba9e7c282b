"""Triton GPU kernel of the octree renderer (forward) and of its analytic backward.

Same semantics as the torch twin ``render/_torch_impl.py`` (read its docstring for the
algorithm): the ray geometry (tree-space origin/direction, box entry/exit, ``step_eps`` push,
quantised leaf lookup, leaf exit) is float64 as in the twin and the numba kernel, so every
backend picks the same leaves; colours and compositing use the dtype of ``data``.

One program marches ``BLOCK`` rays side by side: each loop iteration advances every still
active ray by one leaf segment (a per-lane descent from the root, masked, until every lane has
reached its leaf), so the data-dependent per-ray loop becomes a masked loop over the block that
ends when the block's last ray stops.

``BACKWARD`` (constexpr) turns the same march into the fine-tuning gradient (paper B.3, as in
``optim/_render_grad_numba.py``): given ``g = dL/dC`` and the forward colour ``C``, it walks the
segments again front to back with the running transmittance ``T_i`` and prefix
``P_i = sum_{k<=i} w_k c_k`` and scatters with atomic adds

* ``dL/dk_{ch,b} += g_ch w_i c_ch (1 - c_ch) Y_b``,
* ``dL/dsigma_i += delta_i sum_ch g_ch (c_ch T_{i+1} - (C_ch - P_ch))`` (only where sigma > 0).

Entry points take torch tensors on one device (CUDA, or CPU in interpreter mode) and are called
by :func:`plenoctree.render.render_rays` (``backend="triton"``) and by
:mod:`plenoctree.optim._triton_grad`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
import triton
import triton.language as tl

from .options import KIND_RGBA, QUANT_BITS, RenderOptions, RenderOutput, parse_data_format

__all__ = ["render_rays_triton", "prepare_rays", "march_kernel_call"]

_SCALE = float(2 ** QUANT_BITS)
_BIG = 1e30
BLOCK = 64
assert QUANT_BITS == 30, "the kernel hard-codes 2**30 as its quantisation scale"


@triton.jit
def _march_kernel(child_ptr, data_ptr, basis_ptr, geo_ptr, grad_ptr, crgb_ptr,
                  rgb_ptr, depth_ptr, alpha_ptr, gdata_ptr, n_rays, stop_thresh: tl.float64,
                  bg_r: tl.float64, bg_g: tl.float64, bg_b: tl.float64,
                  D: tl.constexpr, B: tl.constexpr, BP: tl.constexpr, QB: tl.constexpr,
                  BACKWARD: tl.constexpr, BLOCK: tl.constexpr, RENORM: tl.constexpr = False):
    pid = tl.program_id(0)
    ray = pid * BLOCK + tl.arange(0, BLOCK)
    valid = ray < n_rays
    # geo rows (float64, 14 values): o_t[3], d_t[3], inv_d[3], t0, t1, eps_t, pad[2]
    g = geo_ptr + ray.to(tl.int64) * 14
    ox = tl.load(g + 0, mask=valid, other=0.0)
    oy = tl.load(g + 1, mask=valid, other=0.0)
    oz = tl.load(g + 2, mask=valid, other=0.0)
    dx = tl.load(g + 3, mask=valid, other=0.0)
    dy = tl.load(g + 4, mask=valid, other=0.0)
    dz = tl.load(g + 5, mask=valid, other=0.0)
    ix = tl.load(g + 6, mask=valid, other=0.0)
    iy = tl.load(g + 7, mask=valid, other=0.0)
    iz = tl.load(g + 8, mask=valid, other=0.0)
    t = tl.load(g + 9, mask=valid, other=0.0)
    t1 = tl.load(g + 10, mask=valid, other=0.0)
    eps = tl.load(g + 11, mask=valid, other=0.0)

    bidx = tl.arange(0, BP)
    bmask = bidx < B
    basis = tl.load(basis_ptr + ray[:, None].to(tl.int64) * B + bidx[None, :],
                    mask=valid[:, None] & bmask[None, :], other=0.0)         # [BLOCK, BP]
    zero = tl.zeros([BLOCK], dtype=basis.dtype)
    # the float scalars are float64 arguments (a Python float is otherwise passed as float32 to
    # a compiled kernel, but kept float64 by the interpreter) used in the data's dtype, as the
    # twin uses them: float64 data sees the exact background and threshold
    stop = tl.full([BLOCK], stop_thresh, basis.dtype)
    back_r = tl.full([BLOCK], bg_r, basis.dtype)
    back_g = tl.full([BLOCK], bg_g, basis.dtype)
    back_b = tl.full([BLOCK], bg_b, basis.dtype)
    trans = zero + 1.0
    acc_r = zero
    acc_g = zero
    acc_b = zero
    w_sum = zero
    wt_sum = zero
    if BACKWARD:
        gr = tl.load(grad_ptr + ray * 3 + 0, mask=valid, other=0.0).to(basis.dtype)
        gg = tl.load(grad_ptr + ray * 3 + 1, mask=valid, other=0.0).to(basis.dtype)
        gb = tl.load(grad_ptr + ray * 3 + 2, mask=valid, other=0.0).to(basis.dtype)
        cr = tl.load(crgb_ptr + ray * 3 + 0, mask=valid, other=0.0).to(basis.dtype)
        cg = tl.load(crgb_ptr + ray * 3 + 1, mask=valid, other=0.0).to(basis.dtype)
        cb = tl.load(crgb_ptr + ray * 3 + 2, mask=valid, other=0.0).to(basis.dtype)

    active = valid & (t < t1)
    scale = 1073741824.0   # 2 ** QB (QB = 30): exact in float32, so exact in float64 too
    while tl.sum(active.to(tl.int32), axis=0) > 0:
        # locate the leaf holding p(t + eps): masked per-lane descent from the root
        tq = t + eps
        # clamp(p * 2^QB, 0, 2^QB - 1) then truncate, as the twin; the upper clamp is done on
        # the integer (2^QB - 1 is not a float32 constant, and Triton literals are float32)
        qmax = (1 << QB) - 1
        qx = tl.minimum(tl.minimum(tl.maximum((ox + tq * dx) * scale, 0.0), 2.0 * scale)
                        .to(tl.int64), qmax)
        qy = tl.minimum(tl.minimum(tl.maximum((oy + tq * dy) * scale, 0.0), 2.0 * scale)
                        .to(tl.int64), qmax)
        qz = tl.minimum(tl.minimum(tl.maximum((oz + tq * dz) * scale, 0.0), 2.0 * scale)
                        .to(tl.int64), qmax)
        node = tl.zeros([BLOCK], dtype=tl.int64)
        level = tl.zeros([BLOCK], dtype=tl.int64)
        cell = tl.zeros([BLOCK], dtype=tl.int64)
        desc = active
        while tl.sum(desc.to(tl.int32), axis=0) > 0:
            sh = QB - 1 - level
            c = node * 8 + ((qx >> sh) & 1) * 4 + ((qy >> sh) & 1) * 2 + ((qz >> sh) & 1)
            cell = tl.where(desc, c, cell)
            step = tl.load(child_ptr + cell, mask=desc, other=0).to(tl.int64)
            node = node + step
            level = tl.where(step != 0, level + 1, level)
            desc = desc & (step != 0) & (level < QB - 1)
        # exit distance of the leaf's box
        sh = QB - 1 - level
        size = (tl.full([BLOCK], 1, tl.int64) << sh).to(tl.float64) / scale
        lx = ((qx >> sh) << sh).to(tl.float64) / scale
        ly = ((qy >> sh) << sh).to(tl.float64) / scale
        lz = ((qz >> sh) << sh).to(tl.float64) / scale
        bx = tl.where(dx >= 0, lx + size, lx)
        by = tl.where(dy >= 0, ly + size, ly)
        bz = tl.where(dz >= 0, lz + size, lz)
        t_exit = tl.minimum(tl.minimum((bx - ox) * ix, (by - oy) * iy), (bz - oz) * iz)
        t_end = tl.minimum(tl.maximum(t_exit, t + eps), t1)
        delta = (t_end - t).to(basis.dtype)

        row = data_ptr + cell * D
        sig_raw = tl.load(row + (D - 1), mask=active, other=0.0).to(basis.dtype)
        sigma = tl.maximum(sig_raw, 0.0)
        att = tl.exp(-sigma * delta)
        w = trans * (1.0 - att)
        m2 = active[:, None] & bmask[None, :]
        kr = tl.load(row[:, None] + (0 * B) + bidx[None, :], mask=m2, other=0.0).to(basis.dtype)
        kg = tl.load(row[:, None] + (1 * B) + bidx[None, :], mask=m2, other=0.0).to(basis.dtype)
        kb = tl.load(row[:, None] + (2 * B) + bidx[None, :], mask=m2, other=0.0).to(basis.dtype)
        c_r = 1.0 / (1.0 + tl.exp(-tl.sum(kr * basis, axis=1)))
        c_g = 1.0 / (1.0 + tl.exp(-tl.sum(kg * basis, axis=1)))
        c_b = 1.0 / (1.0 + tl.exp(-tl.sum(kb * basis, axis=1)))
        w = tl.where(active, w, 0.0)
        acc_r += w * c_r
        acc_g += w * c_g
        acc_b += w * c_b
        trans_next = tl.where(active, trans * att, trans)
        if BACKWARD:
            hit = active & (sig_raw > 0)
            mh = hit[:, None] & bmask[None, :]
            gd = gdata_ptr + cell * D
            f_r = gr * w * c_r * (1.0 - c_r)
            f_g = gg * w * c_g * (1.0 - c_g)
            f_b = gb * w * c_b * (1.0 - c_b)
            tl.atomic_add(gd[:, None] + (0 * B) + bidx[None, :], f_r[:, None] * basis, mask=mh)
            tl.atomic_add(gd[:, None] + (1 * B) + bidx[None, :], f_g[:, None] * basis, mask=mh)
            tl.atomic_add(gd[:, None] + (2 * B) + bidx[None, :], f_b[:, None] * basis, mask=mh)
            gs = delta * (gr * (c_r * trans_next - (cr - acc_r))
                          + gg * (c_g * trans_next - (cg - acc_g))
                          + gb * (c_b * trans_next - (cb - acc_b)))
            tl.atomic_add(gd + (D - 1), gs, mask=hit)
        else:
            w_sum += w
            wt_sum += w * (0.5 * (t + t_end)).to(basis.dtype)
        trans = trans_next
        t = tl.where(active, t_end, t)
        active = active & (t_end < t1) & (trans >= stop)

    if not BACKWARD:
        out_r = acc_r + trans * back_r
        out_g = acc_g + trans * back_g
        out_b = acc_b + trans * back_b
        opacity = 1.0 - trans
        if RENORM:      # svox's fast rule for the rays stopped early (RenderOptions.renormalize)
            early = trans < stop
            keep = tl.where(early, opacity, zero + 1.0)     # no division by 0 in other lanes
            out_r = tl.where(early, acc_r / keep, out_r)
            out_g = tl.where(early, acc_g / keep, out_g)
            out_b = tl.where(early, acc_b / keep, out_b)
            opacity = tl.where(early, zero + 1.0, opacity)
        tl.store(rgb_ptr + ray * 3 + 0, out_r, mask=valid)
        tl.store(rgb_ptr + ray * 3 + 1, out_g, mask=valid)
        tl.store(rgb_ptr + ray * 3 + 2, out_b, mask=valid)
        tl.store(depth_ptr + ray, wt_sum / tl.maximum(w_sum, 1e-10), mask=valid)
        tl.store(alpha_ptr + ray, opacity, mask=valid)


def _block() -> int:
    """Rays per program: one lane per ray on the GPU; wide blocks in the (per-op) interpreter."""
    from .._triton import interpret_mode

    return 512 if interpret_mode() else BLOCK


def _launch_opts() -> dict:
    """GPU launch options: 2 warps = 64 lanes, one per ray of the block (not for the interpreter)."""
    from .._triton import interpret_mode

    return {} if interpret_mode() else {"num_warps": 2}


def prepare_rays(offset: Any, invradius: Any, origins: torch.Tensor, dirs: torch.Tensor,
                 step_eps: float, box: tuple[torch.Tensor, torch.Tensor] | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-ray float64 geometry ``[N, 14]`` and unit directions ``[N, 3]`` (float64);
    ``box``: ``(offset, invradius)`` as float64 tensors on the rays' device already (a
    ``DeviceTree``'s ``box``: no upload per frame).

    Columns: tree-space origin ``o_t`` (3), per-unit-``t`` direction ``d_t`` (3), ``1 / d_t``
    with zero components replaced by ``1e30`` (3), box entry ``t0``, exit ``t1``,
    ``eps_t = step_eps / |d_t|``, two unused. Computed exactly as the twin does.
    """
    from ._torch_impl import box_intersect_torch

    dev = origins.device
    geo = torch.float64
    if box is not None:
        off, inv = box
    else:
        off = torch.as_tensor(np.asarray(offset, dtype=np.float64).reshape(-1), device=dev)
        inv = torch.as_tensor(np.asarray(invradius, dtype=np.float64).reshape(-1), device=dev)
    o = origins.to(geo).reshape(-1, 3)
    d = dirs.to(geo).reshape(-1, 3)
    d = d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)
    o_t = off + inv * o
    d_t = inv * d
    eps_t = step_eps / torch.linalg.vector_norm(d_t, dim=-1)
    t0, t1 = box_intersect_torch(o_t, d_t)
    d_safe = torch.where(d_t == 0, torch.full_like(d_t, 1.0 / _BIG), d_t)
    out = torch.zeros(o.shape[0], 14, dtype=geo, device=dev)
    out[:, 0:3], out[:, 3:6], out[:, 6:9] = o_t, d_t, 1.0 / d_safe
    out[:, 9], out[:, 10], out[:, 11] = t0, t1, eps_t
    return out.contiguous(), d


def march_kernel_call(child: torch.Tensor, data2: torch.Tensor, basis: torch.Tensor,
                      geo: torch.Tensor, opts: RenderOptions, n_b: int,
                      grad_rgb: torch.Tensor | None = None, rgb_fwd: torch.Tensor | None = None
                      ) -> Any:
    """Launch the march kernel on ``N`` rays.

    ``child`` int32 ``[n_cells]``, ``data2`` float ``[n_cells, D]`` (float32/float64),
    ``basis`` ``[N, B]`` in the dtype of ``data2``, ``geo`` from :func:`prepare_rays`.
    Forward (``grad_rgb is None``): returns ``(rgb [N, 3], depth [N], alpha [N])``.
    Backward: returns ``grad [n_cells, D]`` (same dtype as ``data2``).
    """
    n = geo.shape[0]
    d_dim = data2.shape[1]
    dev, dt = data2.device, data2.dtype
    bp = max(triton.next_power_of_2(n_b), 2)
    block = _block()
    grid = (triton.cdiv(max(n, 1), block),)
    bg = [float(v) for v in opts.background]
    if grad_rgb is None:
        rgb = torch.empty(n, 3, dtype=dt, device=dev)
        depth = torch.empty(n, dtype=dt, device=dev)
        alpha = torch.empty(n, dtype=dt, device=dev)
        if n:
            _march_kernel[grid](child, data2, basis, geo, rgb, rgb, rgb, depth, alpha, data2,
                                n, float(opts.stop_thresh), bg[0], bg[1], bg[2],
                                D=d_dim, B=n_b, BP=bp, QB=QUANT_BITS, BACKWARD=False,
                                BLOCK=block, RENORM=bool(opts.renormalize), **_launch_opts())
        return rgb, depth, alpha
    grad = torch.zeros_like(data2)
    if n:
        g = grad_rgb.to(dt).contiguous()
        c = rgb_fwd.to(dt).contiguous()
        _march_kernel[grid](child, data2, basis, geo, g, c, g, g, g, grad,
                            n, float(opts.stop_thresh), bg[0], bg[1], bg[2],
                            D=d_dim, B=n_b, BP=bp, QB=QUANT_BITS, BACKWARD=True, BLOCK=block,
                            **_launch_opts())
    return grad


def tree_tensors(child: Any, data: Any, device: torch.device
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """``child`` int32 ``[n_cells]`` and ``data`` ``[n_cells, D]`` (float32 unless float64)."""
    ch = child if isinstance(child, torch.Tensor) else torch.from_numpy(np.ascontiguousarray(child))
    ch = ch.to(device=device, dtype=torch.int32).reshape(-1).contiguous()
    dt = data if isinstance(data, torch.Tensor) else torch.from_numpy(np.ascontiguousarray(data))
    if dt.dtype != torch.float64:
        dt = dt.to(torch.float32)
    dt = dt.to(device).reshape(ch.shape[0], -1).contiguous()
    return ch, dt


def render_rays_triton(tree: Any, origins: torch.Tensor, dirs: torch.Tensor,
                       options: RenderOptions | None = None, data: Any = None) -> RenderOutput:
    """Render ``[N, 3]`` rays on their device; same arguments and result as the twin
    (:func:`plenoctree.render._torch_impl.render_rays_torch`).

    ``data`` (default ``tree.data``) float16 is computed in float32; float64 data is rendered in
    float64.
    """
    from .._util import vec3
    from ._torch_impl import ray_basis_torch

    opts = (options or RenderOptions()).validated()
    dev = origins.device
    extra_data = getattr(tree, "extra_data", None)
    ch, d2 = tree_tensors(tree.child, tree.data if data is None else data, dev)
    info = parse_data_format(tree.data_format, d2.shape[1], extra_data)
    geo, unit = prepare_rays(vec3(tree.offset), vec3(tree.invradius), origins, dirs,
                             opts.step_eps)
    basis = ray_basis_torch(info, unit, extra_data, opts).to(d2.dtype).contiguous()
    n_b = 1 if info.kind == KIND_RGBA else info.basis_dim
    rgb, depth, alpha = march_kernel_call(ch, d2, basis, geo, opts, n_b)
    return RenderOutput(rgb=rgb, depth=depth, alpha=alpha)


def render_backend(tree: Any, info: Any, origins: Any, dirs: Any, opts: RenderOptions,
                   device: torch.device) -> RenderOutput:
    """Op ``render`` of :mod:`plenoctree.backend`: rays ``[N, 3]`` on ``device`` (CUDA, or
    the CPU in interpreter mode); numpy rays are moved to ``device``."""
    from .._triton import require_triton

    require_triton(device, "render")
    o = origins if isinstance(origins, torch.Tensor) else torch.from_numpy(origins)
    d = dirs if isinstance(dirs, torch.Tensor) else torch.from_numpy(dirs)
    return render_rays_triton(tree, o.to(device), d.to(device), opts)
