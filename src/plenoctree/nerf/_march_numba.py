"""numba kernels that march rays through an occupancy grid at a fixed step.

Imported lazily by :func:`plenoctree.nerf.sampling.march_rays`; the torch twin
``plenoctree.nerf.sampling._march_torch`` is the specification. For ray ``r`` the candidate
samples are ``t_k = t_min[r] + (jitter[r] + k) · step`` for ``k = k_start[r], k_start[r]+1, …``
while ``t_k < t_max[r]``; sample ``k`` is emitted when the cell of ``o + t_k d`` is occupied.
At most ``max_per_ray`` samples are emitted per call (0 = no limit). All arithmetic is float32
in the same order as the twin, so both emit the same samples.
"""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(inline="always")
def _occupied(px, py, pz, lo, inv, mask, g):
    cx = np.int64(np.floor((px - lo[0]) * inv[0]))
    cy = np.int64(np.floor((py - lo[1]) * inv[1]))
    cz = np.int64(np.floor((pz - lo[2]) * inv[2]))
    if cx < 0 or cy < 0 or cz < 0 or cx >= g or cy >= g or cz >= g:
        return False
    return mask[cx, cy, cz]


@nb.njit(parallel=True, cache=True, nogil=True)
def march_count(origins, dirs, t_min, t_max, jitter, k_start, step, mask, lo, inv,
                max_per_ray, counts, k_next, done):  # pragma: no cover - compiled
    """Pass 1: ``counts[r]`` emitted samples, ``k_next[r]``, ``done[r]`` (see module doc)."""
    g = mask.shape[0]
    for r in nb.prange(origins.shape[0]):
        ox, oy, oz = origins[r, 0], origins[r, 1], origins[r, 2]
        dx, dy, dz = dirs[r, 0], dirs[r, 1], dirs[r, 2]
        t0 = t_min[r]
        t1 = t_max[r]
        jr = jitter[r]
        k = k_start[r]
        n = 0
        while True:
            t = t0 + (jr + np.float32(k)) * step
            if not t < t1:
                break
            if _occupied(ox + t * dx, oy + t * dy, oz + t * dz, lo, inv, mask, g):
                n += 1
                if max_per_ray > 0 and n >= max_per_ray:
                    k += 1
                    break
            k += 1
        counts[r] = n
        k_next[r] = k
        done[r] = not (t0 + (jr + np.float32(k)) * step < t1)


@nb.njit(parallel=True, cache=True, nogil=True)
def march_fill(origins, dirs, t_min, t_max, jitter, k_start, step, mask, lo, inv,
               offsets, ray_idx, ts, pts):  # pragma: no cover - compiled
    """Pass 2: write the samples of ray ``r`` to rows ``offsets[r]:offsets[r+1]``."""
    g = mask.shape[0]
    for r in nb.prange(origins.shape[0]):
        ox, oy, oz = origins[r, 0], origins[r, 1], origins[r, 2]
        dx, dy, dz = dirs[r, 0], dirs[r, 1], dirs[r, 2]
        t0 = t_min[r]
        jr = jitter[r]
        k = k_start[r]
        i = offsets[r]
        end = offsets[r + 1]
        while i < end:
            t = t0 + (jr + np.float32(k)) * step
            px = ox + t * dx
            py = oy + t * dy
            pz = oz + t * dz
            if _occupied(px, py, pz, lo, inv, mask, g):
                ray_idx[i] = r
                ts[i] = t
                pts[i, 0] = px
                pts[i, 1] = py
                pts[i, 2] = pz
                i += 1
            k += 1
