"""Where along each ray the network is evaluated.

* :func:`ray_aabb` — entry/exit distances of rays through a box.
* :func:`stratified_samples`, :func:`pdf_samples` — the paper's hierarchical sampling
  (NeRF: ``n_coarse`` stratified samples, then ``n_fine`` samples drawn from the coarse
  weights by inverse-CDF sampling).
* :func:`march_rays` — the CPU preset's sampler: a fixed step through an occupancy grid,
  emitting only samples in occupied cells, packed ray after ray (numba kernels in
  :mod:`._march_numba`; the torch twin :func:`_march_torch` is the specification and the
  CUDA path). Its rays travel as a :class:`MarchRays`, the lattice as a :class:`MarchGrid`.

All distances ``t`` are along unit directions, world units.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


__all__ = ["ray_aabb", "stratified_samples", "pdf_samples", "PackedSamples", "MarchRays",
           "MarchGrid", "march_rays", "numba_march_args"]


def ray_aabb(origins: torch.Tensor, dirs: torch.Tensor, bbox: torch.Tensor
             ) -> tuple[torch.Tensor, torch.Tensor]:
    """Slab test of rays against an axis-aligned box.

    Args:
        origins, dirs: ``[R, 3]`` (``dirs`` need not be unit; zero components are fine).
        bbox: ``[2, 3]`` min / max corner.

    Returns:
        ``(t_near [R], t_far [R])``; a ray misses the box when ``t_far <= t_near``. ``t_near``
        may be negative (origin inside the box).
    """
    inv = 1.0 / torch.where(dirs == 0, torch.full_like(dirs, 1e-12), dirs)
    t0 = (bbox[0] - origins) * inv
    t1 = (bbox[1] - origins) * inv
    t_near = torch.minimum(t0, t1).amax(-1)
    t_far = torch.maximum(t0, t1).amin(-1)
    return t_near, t_far


def stratified_samples(near: torch.Tensor, far: torch.Tensor, n: int, perturb: bool,
                       generator: torch.Generator | None = None) -> torch.Tensor:
    """NeRF's coarse samples: ``n`` depths per ray, one uniform draw per bin.

    Args:
        near, far: ``[R]`` bounds. n: samples per ray. perturb: jitter within bins (training);
            when False the samples are the evenly spaced ``linspace(near, far, n)``.

    Returns:
        ``t [R, n]`` increasing.
    """
    u = torch.linspace(0.0, 1.0, n, device=near.device, dtype=near.dtype)
    t = near[:, None] * (1.0 - u) + far[:, None] * u
    if perturb:
        mids = 0.5 * (t[:, 1:] + t[:, :-1])
        upper = torch.cat([mids, t[:, -1:]], -1)
        lower = torch.cat([t[:, :1], mids], -1)
        r = torch.rand(t.shape, generator=generator, device=t.device, dtype=t.dtype)
        t = lower + (upper - lower) * r
    return t


def pdf_samples(bins: torch.Tensor, weights: torch.Tensor, n: int, perturb: bool,
                generator: torch.Generator | None = None) -> torch.Tensor:
    """Inverse-CDF samples of the piecewise-constant density given by ``weights`` on ``bins``.

    Args:
        bins: ``[R, S + 1]`` increasing bin edges. weights: ``[R, S]`` non-negative.
        n: samples per ray. perturb: uniform random ``u`` (training) instead of evenly spaced.

    Returns:
        ``t [R, n]`` sorted, inside ``[bins[:, 0], bins[:, -1]]``; no gradient flows.
    """
    bins, weights = bins.detach(), weights.detach()
    w = weights + 1e-5                                    # NeRF: avoid empty pdfs
    pdf = w / w.sum(-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), torch.cumsum(pdf, -1)], -1).clamp(max=1.0)
    if perturb:
        u = torch.rand((bins.shape[0], n), generator=generator, device=bins.device,
                       dtype=bins.dtype)
    else:
        u = torch.linspace(0.0, 1.0, n, device=bins.device, dtype=bins.dtype).expand(
            bins.shape[0], n)
    u = u.contiguous()
    idx = torch.searchsorted(cdf, u, right=True)
    below = (idx - 1).clamp(0, cdf.shape[-1] - 1)
    above = idx.clamp(0, cdf.shape[-1] - 1)
    c0, c1 = cdf.gather(-1, below), cdf.gather(-1, above)
    b0, b1 = bins.gather(-1, below), bins.gather(-1, above)
    denom = torch.where(c1 - c0 < 1e-5, torch.ones_like(c0), c1 - c0)
    t = b0 + (u - c0) / denom * (b1 - b0)
    return torch.sort(t, -1).values


@dataclass
class PackedSamples:
    """Samples of ``R`` rays packed one ray after the other (``M`` in total).

    Attributes:
        ray_idx: int64 ``[M]`` ray of each sample (non-decreasing).
        t: float32 ``[M]`` distance along the ray.
        points: float32 ``[M, 3]`` world positions ``o + t d``.
        offsets: int64 ``[R + 1]``; ray ``r`` owns rows ``offsets[r]:offsets[r + 1]``.
        k_next: int64 ``[R]`` lattice index to continue marching from.
        done: bool ``[R]`` the ray's lattice reached ``t_max``.
    """

    ray_idx: torch.Tensor
    t: torch.Tensor
    points: torch.Tensor
    offsets: torch.Tensor
    k_next: torch.Tensor
    done: torch.Tensor

    @property
    def counts(self) -> torch.Tensor:
        return self.offsets[1:] - self.offsets[:-1]

    def __len__(self) -> int:
        return int(self.t.shape[0])


@dataclass(frozen=True)
class MarchRays:
    """``R`` rays to march and where each one's lattice starts.

    Attributes:
        origins, dirs: float32 ``[R, 3]`` (dirs unit). t_min, t_max: float32 ``[R]`` bounds.
        jitter: float32 ``[R]`` in ``[0, 1)`` (0.5 for deterministic rendering).
        k_start: int64 ``[R]`` first lattice index (None: 0).
    """

    origins: torch.Tensor
    dirs: torch.Tensor
    t_min: torch.Tensor
    t_max: torch.Tensor
    jitter: torch.Tensor
    k_start: torch.Tensor | None = None

    def select(self, idx: torch.Tensor, k_start: torch.Tensor) -> "MarchRays":
        """Rays ``idx`` of these, their lattices starting at ``k_start [len(idx)]``."""
        return MarchRays(self.origins[idx], self.dirs[idx], self.t_min[idx], self.t_max[idx],
                         self.jitter[idx], k_start)

    def contiguous(self) -> "MarchRays":
        """Contiguous float32 tensors, ``k_start`` int64 (zeros when None): the kernels' input."""
        k = self.k_start
        if k is None:
            k = torch.zeros(self.origins.shape[0], dtype=torch.int64, device=self.origins.device)
        f = (lambda x: x.float().contiguous())
        return MarchRays(f(self.origins), f(self.dirs), f(self.t_min), f(self.t_max),
                         f(self.jitter), k.long().contiguous())


@dataclass(frozen=True)
class MarchGrid:
    """The sample lattice: spacing ``step`` (world units) and the occupancy it keeps samples in,
    a bool ``mask [G, G, G]`` (x, y, z) over the box ``bbox [2, 3]``."""

    step: float
    mask: torch.Tensor
    bbox: torch.Tensor


_CONSTS_CACHE: dict = {}


def _grid_consts(mask: torch.Tensor, bbox: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """``(lo [3], inv [3])`` float32 on the host: the box's low corner and cells per world unit.

    Read from ``bbox`` once per box content, not once per march: on a GPU each read is a host
    round trip, and the trainer marches in several waves a step. Like :func:`_empty_levels`
    the cache holds the last ``bbox`` itself and its in-place version counter."""
    g = int(mask.shape[0])
    c = _CONSTS_CACHE
    if c.get("bbox") is bbox and c.get("version") == bbox._version and c.get("g") == g:
        return c["consts"]
    b = bbox.detach().cpu().numpy().astype(np.float32)
    consts = (b[0].copy(), (np.float32(g) / (b[1] - b[0])).astype(np.float32))
    c.update(bbox=bbox, version=bbox._version, g=g, consts=consts)
    return consts


def _march_torch(rays: MarchRays, grid: MarchGrid, max_per_ray: int) -> PackedSamples:
    """Pure-torch twin of the marching kernels (vectorised over a ``[R, K]`` lattice)."""
    origins, dirs, t_min, t_max, jitter, k_start = (
        rays.origins, rays.dirs, rays.t_min, rays.t_max, rays.jitter, rays.k_start)
    mask = grid.mask
    dev = origins.device
    n_rays = origins.shape[0]
    g = mask.shape[0]
    lo_np, inv_np = _grid_consts(mask, grid.bbox)
    lo, inv = torch.as_tensor(lo_np, device=dev), torch.as_tensor(inv_np, device=dev)
    step32 = torch.tensor(grid.step, dtype=torch.float32, device=dev)
    span = ((t_max - t_min) / step32 - jitter).clamp(min=0) + 2 - k_start.float()
    kmax = int(span.max().item()) + 1 if n_rays else 1
    k = k_start[:, None] + torch.arange(max(kmax, 1), device=dev)[None, :]       # [R, K]
    t = t_min[:, None] + (jitter[:, None] + k.float()) * step32
    valid = t < t_max[:, None]
    # t_k increases with k, so the lattice stops at the first k with t_k >= t_max
    valid = torch.cumprod(valid.to(torch.int32), dim=1).bool()
    p = origins[:, None, :] + t[..., None] * dirs[:, None, :]                      # [R, K, 3]
    c = torch.floor((p - lo) * inv).long()
    inside = ((c >= 0) & (c < g)).all(-1)
    cc = c.clamp(0, g - 1)
    occ = mask[cc[..., 0], cc[..., 1], cc[..., 2]] & inside & valid
    rank = torch.cumsum(occ.to(torch.int64), dim=1)                               # 1-based
    if max_per_ray > 0:
        emit = occ & (rank <= max_per_ray)
        capped = occ & (rank == max_per_ray)                    # the last emitted sample
        has_cap = capped.any(1)
        k_cap = torch.where(capped, k, torch.zeros_like(k)).amax(1) + 1
    else:
        emit = occ
        has_cap = torch.zeros(n_rays, dtype=torch.bool, device=dev)
        k_cap = k_start
    n_valid = valid.sum(1)
    k_end = k_start + n_valid
    k_next = torch.where(has_cap, k_cap, k_end)
    t_next = t_min + (jitter + k_next.float()) * step32
    done = ~(t_next < t_max)
    counts = emit.sum(1)
    offsets = torch.cat([torch.zeros(1, dtype=torch.int64, device=dev), torch.cumsum(counts, 0)])
    rows, cols = emit.nonzero(as_tuple=True)                                      # row-major
    return PackedSamples(rows, t[rows, cols], p[rows, cols], offsets, k_next, done)


def march_rays(rays: MarchRays, grid: MarchGrid, max_per_ray: int = 0,
               backend: str = "auto") -> PackedSamples:
    """March rays at a fixed step, keeping samples in occupied cells.

    Candidate samples of ray ``r`` are ``t_k = t_min[r] + (jitter[r] + k)·step`` for
    ``k = k_start[r], …`` while ``t_k < t_max[r]``; a sample is kept when the cell of
    ``origins[r] + t_k dirs[r]`` in the grid ``grid.mask`` over ``grid.bbox`` is occupied.

    Args:
        rays: the rays and where their lattices start. grid: spacing and occupancy.
        max_per_ray: emit at most this many samples per ray (0 = all).
        backend: "auto" (numba on CPU), "numba" or "torch".

    Returns:
        :class:`PackedSamples`.
    """
    rays = rays.contiguous()
    from .. import backend as _backend

    name = _backend.resolve("march", backend, rays.origins.device)
    return _backend.implementation("march", name)(rays, grid, max_per_ray)


_LEVELS_CACHE: dict = {}


def _empty_levels(mask: torch.Tensor) -> tuple[np.ndarray, np.ndarray, int]:
    """:func:`._march_numba.empty_levels` of a CPU ``mask`` and its
    :func:`~._march_numba.coarse_levels` (+ their shift), computed once per mask content: the
    trainer marches ~3 times a step and updates its grid in place every 16 steps. The cache
    holds the last mask itself (so its memory cannot be reused by another tensor) and its
    in-place version counter (bumped by every torch write to it)."""
    from . import _march_numba as K

    if _LEVELS_CACHE.get("mask") is mask and _LEVELS_CACHE.get("version") == mask._version:
        return _LEVELS_CACHE["levels"]
    g = int(mask.shape[0])
    levels = np.empty((g, g, g), np.uint8)
    K.empty_levels(mask.contiguous().numpy(), levels)
    cs = K.coarse_shift(g)
    coarse = np.empty((g >> cs,) * 3, np.uint8)
    K.coarse_levels(levels, cs, coarse)
    _LEVELS_CACHE.update(mask=mask, version=mask._version, levels=(levels, coarse, cs))
    return levels, coarse, cs


def numba_march_args(rays: MarchRays, grid: MarchGrid) -> tuple[tuple, tuple]:
    """``(args, outs)`` of the numba kernels :func:`._march_numba.march_count` /
    ``march_fill`` for contiguous CPU ``rays``: the rays, step, empty levels and box; and the
    empty ``(counts, k_next, done)`` arrays of the counting pass."""
    n_rays = rays.origins.shape[0]
    lo, inv = _grid_consts(grid.mask, grid.bbox)
    levels, coarse, cs = _empty_levels(grid.mask)
    args = (rays.origins.numpy(), rays.dirs.numpy(), rays.t_min.numpy(), rays.t_max.numpy(),
            rays.jitter.numpy(), rays.k_start.numpy(), np.float32(grid.step), levels, coarse,
            np.int64(cs), lo, inv)
    return args, (np.empty(n_rays, np.int64), np.empty(n_rays, np.int64),
                  np.empty(n_rays, np.bool_))


def _march_numba(rays: MarchRays, grid: MarchGrid, max_per_ray: int) -> PackedSamples:
    """The numba marching kernels (CPU tensors); the same samples as :func:`_march_torch`,
    crossing empty cubes of the grid in jumps (see :mod:`._march_numba`)."""
    from . import _march_numba as K

    n_rays = rays.origins.shape[0]
    args, (counts, k_next, done) = numba_march_args(rays, grid)
    K.march_count(*args, int(max_per_ray), counts, k_next, done)
    offsets = np.zeros(n_rays + 1, np.int64)
    np.cumsum(counts, out=offsets[1:])
    total = int(offsets[-1])
    ray_idx = np.empty(total, np.int64)
    ts = np.empty(total, np.float32)
    pts = np.empty((total, 3), np.float32)
    K.march_fill(*args, offsets, ray_idx, ts, pts)
    return PackedSamples(torch.from_numpy(ray_idx), torch.from_numpy(ts), torch.from_numpy(pts),
                         torch.from_numpy(offsets), torch.from_numpy(k_next),
                         torch.from_numpy(done))
