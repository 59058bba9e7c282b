"""Triton GPU kernels that march rays through an occupancy grid at a fixed step.

Same samples as the torch twin ``sampling._march_torch`` and the numba kernels
(``_march_numba``): candidate ``t_k = t_min + (jitter + k) step`` for ``k = k_start, …`` while
``t_k < t_max``; sample ``k`` is kept when the cell ``floor((o + t_k d - lo) inv)`` of the
``[G, G, G]`` mask is occupied; at most ``max_per_ray`` per call (0 = all). Two passes, as on
the CPU: count (→ ``counts``, ``k_next``, ``done``), then fill rows ``offsets[r]:offsets[r+1]``.
All arithmetic is float32 in the twin's order; on the GPU the kernels are compiled without
fused multiply-adds so that every backend emits the same samples.
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

__all__ = ["march_backend"]

BLOCK = 128


@triton.jit
def _march_kernel(o_ptr, d_ptr, tmin_ptr, tmax_ptr, jit_ptr, k0_ptr, mask_ptr, step,
                  lox, loy, loz, ivx, ivy, ivz, G, max_per_ray, n,
                  counts_ptr, knext_ptr, done_ptr, offsets_ptr, ray_ptr, ts_ptr, pts_ptr,
                  FILL: tl.constexpr, BLOCK: tl.constexpr):
    pid = tl.program_id(0)
    r = pid * BLOCK + tl.arange(0, BLOCK)
    valid = r < n
    r64 = r.to(tl.int64)
    ox = tl.load(o_ptr + r64 * 3 + 0, mask=valid, other=0.0)
    oy = tl.load(o_ptr + r64 * 3 + 1, mask=valid, other=0.0)
    oz = tl.load(o_ptr + r64 * 3 + 2, mask=valid, other=0.0)
    dx = tl.load(d_ptr + r64 * 3 + 0, mask=valid, other=0.0)
    dy = tl.load(d_ptr + r64 * 3 + 1, mask=valid, other=0.0)
    dz = tl.load(d_ptr + r64 * 3 + 2, mask=valid, other=0.0)
    t0 = tl.load(tmin_ptr + r, mask=valid, other=0.0)
    t1 = tl.load(tmax_ptr + r, mask=valid, other=0.0)
    jr = tl.load(jit_ptr + r, mask=valid, other=0.0)
    k = tl.load(k0_ptr + r, mask=valid, other=0)
    if FILL:
        i = tl.load(offsets_ptr + r, mask=valid, other=0)
        end = tl.load(offsets_ptr + r + 1, mask=valid, other=0)
        active = valid & (i < end)
    else:
        cnt = tl.zeros([BLOCK], dtype=tl.int64)
        active = valid
    while tl.sum(active.to(tl.int32), axis=0) > 0:
        t = t0 + (jr + k.to(tl.float32)) * step
        px = ox + t * dx
        py = oy + t * dy
        pz = oz + t * dz
        cx = tl.floor((px - lox) * ivx).to(tl.int64)
        cy = tl.floor((py - loy) * ivy).to(tl.int64)
        cz = tl.floor((pz - loz) * ivz).to(tl.int64)
        inside = (cx >= 0) & (cy >= 0) & (cz >= 0) & (cx < G) & (cy < G) & (cz < G)
        cell = (cx * G + cy) * G + cz
        occ = tl.load(mask_ptr + cell, mask=active & inside, other=0) != 0
        if FILL:
            occ = occ & active
            tl.store(ray_ptr + i, r64, mask=occ)
            tl.store(ts_ptr + i, t, mask=occ)
            tl.store(pts_ptr + i * 3 + 0, px, mask=occ)
            tl.store(pts_ptr + i * 3 + 1, py, mask=occ)
            tl.store(pts_ptr + i * 3 + 2, pz, mask=occ)
            i = tl.where(occ, i + 1, i)
            k = tl.where(active, k + 1, k)
            active = active & (i < end)
        else:
            go = active & (t < t1)              # the lattice stops at the first t_k >= t_max
            hit = go & occ
            cnt = tl.where(hit, cnt + 1, cnt)
            capped = hit & (cnt >= max_per_ray)     # (no limit: max_per_ray = 2^62)
            k = tl.where(go, k + 1, k)
            active = go & ~capped
    if not FILL:
        tl.store(counts_ptr + r, cnt, mask=valid)
        tl.store(knext_ptr + r, k, mask=valid)
        tn = t0 + (jr + k.to(tl.float32)) * step
        tl.store(done_ptr + r, (~(tn < t1)).to(tl.int8), mask=valid)


def _passes(rays, grid, what: str, cap: int):
    """``(counts, k_next, done, launch)``: the count pass's outputs (int64 ``[R]``, int64
    ``[R]``, int8 ``[R]``, uninitialised) and ``launch(fill, offsets, ray_idx, ts, pts)``
    running one pass of :func:`_march_kernel` on ``rays`` through ``grid`` (at most ``cap``
    samples a ray in the count pass)."""
    from .._triton import interpret_mode, require_triton
    from .sampling import _grid_consts

    origins, mask = rays.origins, grid.mask
    dev = origins.device
    require_triton(dev, what)
    n = origins.shape[0]
    lo, inv = _grid_consts(mask, grid.bbox)
    counts = torch.empty(n, dtype=torch.int64, device=dev)
    k_next = torch.empty(n, dtype=torch.int64, device=dev)
    done = torch.empty(n, dtype=torch.int8, device=dev)
    block = 1024 if interpret_mode() else BLOCK
    opts = {} if interpret_mode() else {"enable_fp_fusion": False}
    args = (origins, rays.dirs, rays.t_min, rays.t_max, rays.jitter, rays.k_start,
            _mask_int8(mask, dev), float(grid.step), *map(float, lo), *map(float, inv),
            int(mask.shape[0]), int(cap), n)

    def launch(fill: bool, offsets, ray_idx, ts, pts) -> None:
        _march_kernel[(triton.cdiv(max(n, 1), block),)](
            *args, counts, k_next, done, offsets, ray_idx, ts, pts, FILL=fill, BLOCK=block,
            **opts)
    return counts, k_next, done, launch


def march_backend(rays, grid, max_per_ray: int):
    """Op ``march`` of :mod:`plenoctree.backend` (tensors on CUDA, or the CPU in the
    interpreter): :class:`~plenoctree.nerf.sampling.MarchRays` through a
    :class:`~plenoctree.nerf.sampling.MarchGrid`; returns
    :class:`~plenoctree.nerf.sampling.PackedSamples`."""
    from .sampling import PackedSamples

    dev, n = rays.origins.device, rays.origins.shape[0]
    counts, k_next, done, launch = _passes(rays, grid, "march_rays",
                                           int(max_per_ray) if max_per_ray > 0 else 1 << 62)
    if n:
        launch(False, counts, counts, counts, counts)
    offsets = torch.zeros(n + 1, dtype=torch.int64, device=dev)
    torch.cumsum(counts, 0, out=offsets[1:])
    total = int(offsets[-1].item()) if n else 0
    ray_idx = torch.empty(total, dtype=torch.int64, device=dev)
    ts = torch.empty(total, dtype=torch.float32, device=dev)
    pts = torch.empty((total, 3), dtype=torch.float32, device=dev)
    if total:
        launch(True, offsets, ray_idx, ts, pts)
    return PackedSamples(ray_idx, ts, pts, offsets, k_next, done.bool())


def march_fixed_backend(rays, grid, capacity: int):
    """Op ``march_fixed`` of :mod:`plenoctree.backend`: the two passes above into the fixed
    buffers of a sample budget (:func:`plenoctree.nerf.fixed.march_fixed`), with no read-back
    (the prefix sum is cut at the budget on the device)."""
    from .fixed import _samples, finish_fixed, fixed_buffers

    n = rays.origins.shape[0]
    counts, k_next, done, launch = _passes(rays, grid, "march_fixed", 1 << 62)
    launch(False, counts, counts, counts, counts)
    cut, full = finish_fixed(counts, capacity)
    ray_idx, ts, pts = fixed_buffers(n, capacity, grid.bbox)
    launch(True, cut, ray_idx, ts, pts)
    return _samples(ray_idx, ts, pts, cut, full, capacity)


_MASK_CACHE: dict = {}


def _mask_int8(mask: torch.Tensor, dev: torch.device) -> torch.Tensor:
    """The occupancy mask as flat int8 on ``dev``, converted once per mask content (the grid
    changes every ``occ_update_every`` steps, in place: its version counter says when)."""
    c = _MASK_CACHE
    if c.get("mask") is mask and c.get("version") == mask._version:
        return c["m"]
    m = mask.to(device=dev, dtype=torch.int8).contiguous().reshape(-1)
    c.update(mask=mask, version=mask._version, m=m)
    return m
