"""Triton kernels of early ray termination in fixed shapes (op ``terminate``, issue 47).

The twin (:func:`.fixed._terminate_torch`) finds each ray's kept candidates with batch-wide
prefix sums over the ``k S`` candidate slots (~35 ops). Here each ray walks its own candidates
(rays are the lanes of a program, as in the march's kernels):

1. ``count``: ``D += σ_i δ`` in float64 along the ray's slots ``offsets[r]:offsets[r + 1]``;
   candidate ``i`` is kept while the optical depth before it is ``≤ -log(stop_thresh)`` (a
   prefix of the ray: σ ≥ 0); the ray's kept count is written;
2. a prefix sum of the counts (one torch op), the kept samples' first slot of each ray;
3. ``fill``: each ray copies its kept candidates (ray, t, point) to slots ``first + j`` below
   the budget ``S``; the programs past the rays write the unfilled slots (those from the total
   kept on, read on the device) as unfilled slots are: the dummy ray ``R``, t 0, the box's
   centre. Every output slot is written: no buffer is filled beforehand.

Same kept sets as the twin and as a per-ray Python loop (the twin subtracts batch-wide prefix
sums, so a candidate whose depth lies within ~1e-16 of the threshold may fall either way).
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

__all__ = ["terminate_backend"]

BLOCK = 128


@triton.jit
def _terminate_kernel(off_ptr, sig_ptr, ray_ptr, t_ptr, pts_ptr, first_ptr, box_ptr,
                      count_ptr, oray_ptr, ot_ptr, opts_ptr, consts_ptr, n, cap,
                      FILL: tl.constexpr, BLOCK: tl.constexpr):
    pid = tl.program_id(0)
    n_ray_progs = tl.cdiv(n, BLOCK)
    if pid < n_ray_progs:
        r = pid * BLOCK + tl.arange(0, BLOCK)
        valid = r < n
        i = tl.load(off_ptr + r, mask=valid, other=0)
        end = tl.load(off_ptr + r + 1, mask=valid, other=0)
        step = tl.load(consts_ptr)                  # float64, as the twin's
        limit = tl.load(consts_ptr + 1)
        depth = tl.zeros([BLOCK], dtype=tl.float64)
        cnt = tl.zeros([BLOCK], dtype=tl.int64)
        if FILL:
            dest = tl.load(first_ptr + r, mask=valid, other=0)
            todo = tl.load(count_ptr + r, mask=valid, other=0)
            active = valid & (cnt < todo) & (dest < cap)
        else:
            active = valid & (i < end)
        while tl.sum(active.to(tl.int32), axis=0) > 0:
            if FILL:
                tl.store(oray_ptr + dest, tl.load(ray_ptr + i, mask=active, other=0),
                         mask=active)
                tl.store(ot_ptr + dest, tl.load(t_ptr + i, mask=active, other=0.0),
                         mask=active)
                for a in tl.static_range(3):
                    tl.store(opts_ptr + dest * 3 + a,
                             tl.load(pts_ptr + i * 3 + a, mask=active, other=0.0), mask=active)
                cnt = tl.where(active, cnt + 1, cnt)
                dest = tl.where(active, dest + 1, dest)
                i = tl.where(active, i + 1, i)
                active = active & (cnt < todo) & (dest < cap)
            else:
                sig = tl.load(sig_ptr + i, mask=active, other=0.0).to(tl.float64)
                cnt = tl.where(active, cnt + 1, cnt)         # kept: its depth before <= limit
                depth = tl.where(active, depth + sig * step, depth)
                i = tl.where(active, i + 1, i)
                active = active & (i < end) & (depth <= limit)
        if not FILL:
            tl.store(count_ptr + r, cnt, mask=valid)
    elif FILL:                       # the unfilled slots: from the total kept to the budget
        s = (pid - n_ray_progs) * BLOCK + tl.arange(0, BLOCK)
        kept = tl.load(first_ptr + n)
        todo = (s < cap) & (s >= kept)
        s64 = s.to(tl.int64)
        tl.store(oray_ptr + s64, tl.zeros([BLOCK], dtype=tl.int64) + n, mask=todo)
        tl.store(ot_ptr + s64, tl.zeros([BLOCK], dtype=tl.float32), mask=todo)
        for a in tl.static_range(3):
            c = 0.5 * (tl.load(box_ptr + a) + tl.load(box_ptr + 3 + a))
            tl.store(opts_ptr + s64 * 3 + a, tl.zeros([BLOCK], dtype=tl.float32) + c, mask=todo)


_CONSTS: dict = {}


def _consts(step: float, limit: float, dev: torch.device) -> torch.Tensor:
    """float64 ``[step, limit]`` on ``dev``, uploaded once per value pair (a Triton float
    argument would be rounded to float32; an upload per call is a host round trip)."""
    key = (float(step), float(limit), str(dev))
    out = _CONSTS.get(key)
    if out is None:
        out = _CONSTS[key] = torch.tensor([step, limit], dtype=torch.float64, device=dev)
    return out


def terminate_backend(cand, sigma: torch.Tensor, grid, stop_thresh: float, capacity: int):
    """Op ``terminate`` of :mod:`plenoctree.backend` (CUDA tensors, or the CPU in the
    interpreter): :func:`.fixed.terminate_fixed`'s contract in two launches and a prefix sum."""
    import math

    from .._triton import interpret_mode, require_triton
    from .fixed import FixedSamples

    dev = cand.t.device
    require_triton(dev, "terminate")
    n = cand.complete.shape[0]
    off = cand.offsets.contiguous()
    sig = sigma.detach().contiguous()
    box = grid.bbox.float().contiguous()
    counts = torch.empty(n, dtype=torch.int64, device=dev)
    first = torch.zeros(n + 1, dtype=torch.int64, device=dev)
    ray_idx = torch.empty(capacity, dtype=torch.int64, device=dev)
    ts = torch.empty(capacity, dtype=torch.float32, device=dev)
    pts = torch.empty((capacity, 3), dtype=torch.float32, device=dev)
    block = 1024 if interpret_mode() else BLOCK
    args = (off, sig, cand.ray_idx, cand.t, cand.points, first, box, counts, ray_idx, ts, pts,
            _consts(float(grid.step), -math.log(stop_thresh), dev), n, int(capacity))
    ray_progs = triton.cdiv(max(n, 1), block)
    _terminate_kernel[(ray_progs,)](*args, FILL=False, BLOCK=block)
    torch.cumsum(counts, 0, out=first[1:])
    _terminate_kernel[(ray_progs + triton.cdiv(capacity, block),)](*args, FILL=True,
                                                                  BLOCK=block)
    cut = first.clamp(max=capacity)
    end = torch.full((1,), capacity, dtype=torch.int64, device=dev)
    return FixedSamples(ray_idx, ts, pts, torch.cat([cut, end]),
                        cand.complete & (first[1:] <= capacity), cut[-1], cand.total)
