"""numba kernels that march rays through an occupancy grid at a fixed step.

Imported lazily by :func:`plenoctree.nerf.sampling.march_rays`; the torch twin
``plenoctree.nerf.sampling._march_torch`` is the specification. For ray ``r`` the candidate
samples are ``t_k = t_min[r] + (jitter[r] + k) · step`` for ``k = k_start[r], k_start[r]+1, …``
while ``t_k < t_max[r]``; sample ``k`` is emitted when the cell of ``o + t_k d`` is occupied.
At most ``max_per_ray`` samples are emitted per call (0 = no limit). All arithmetic is float32
in the same order as the twin, so both emit the same samples.

Empty space is crossed in jumps: :func:`empty_levels` gives each empty cell the level ``l`` of
the largest aligned ``2^l``-cell cube around it that holds no occupied cell, and a candidate
that lands in one jumps to the last lattice index that is surely still inside that cube (at
least :data:`MARGIN` cells from its faces, and one step before the cube's exit — far beyond
float32 rounding), so the samples that are evaluated and emitted are exactly the twin's.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

#: An occupied cell in :func:`empty_levels`'s array.
OCCUPIED = 255
#: A cube of :func:`coarse_levels` that is not one empty cube (look at its cells).
MIXED = 254
#: Cells per axis of one :func:`coarse_levels` cube (as a shift), at most.
COARSE_SHIFT = 3
#: Cells: how far inside an empty cube a point must lie to be skipped from (float32 rounding
#: of a point is ~1e-5 cells on a 128-cell grid).
MARGIN = 1e-3


@nb.njit(cache=True, nogil=True)
def empty_levels(mask, out):  # pragma: no cover - compiled
    """``out[x, y, z]`` (uint8, same shape as the bool ``mask [G, G, G]``): :data:`OCCUPIED`
    for an occupied cell, else the largest ``l`` such that the aligned cube of ``2^l`` cells
    holding the cell is empty (cubes while ``G`` divides by ``2^l``)."""
    g = mask.shape[0]
    for i in range(g):
        for j in range(g):
            for k in range(g):
                out[i, j, k] = OCCUPIED if mask[i, j, k] else 0
    lev = 1
    while g % (1 << lev) == 0 and (1 << lev) <= g:
        s = 1 << lev
        h = s >> 1
        for bi in range(0, g, s):
            for bj in range(0, g, s):
                for bk in range(0, g, s):
                    empty = True
                    for c in range(8):
                        v = out[bi + (c >> 2) * h, bj + ((c >> 1) & 1) * h, bk + (c & 1) * h]
                        if v == OCCUPIED or v < lev - 1:
                            empty = False
                            break
                    if empty:
                        for i in range(bi, bi + s):
                            for j in range(bj, bj + s):
                                for k in range(bk, bk + s):
                                    out[i, j, k] = lev
        lev += 1


def coarse_shift(g: int) -> int:
    """log2 of the cells per axis of a :func:`coarse_levels` cube for a ``g``-cell grid."""
    cs = 0
    while cs < COARSE_SHIFT and g % (2 << cs) == 0:
        cs += 1
    return cs


@nb.njit(cache=True, nogil=True)
def coarse_levels(levels, cs, out):  # pragma: no cover - compiled
    """``out [G >> cs]³`` (uint8): the level shared by all cells of each aligned ``2^cs``-cell
    cube when the cube is empty (its cells then all lie in the same largest empty cube),
    :data:`MIXED` otherwise. 4 KB for a 128³ grid: the empty-space lookups of a march stay in
    the first-level cache instead of missing in the 2 MB ``levels`` array at every jump."""
    gc = out.shape[0]
    for i in range(gc):
        for j in range(gc):
            for k in range(gc):
                v = levels[i << cs, j << cs, k << cs]
                out[i, j, k] = v if v != OCCUPIED and v >= cs else MIXED


@nb.njit(inline="always")
def _cell_level(px, py, pz, lo, inv, levels, coarse, cs, g):
    """Grid coordinates of a point and the :func:`empty_levels` value of its cell (looked up
    in ``coarse`` first; -1 for a point outside the grid)."""
    ux = (px - lo[0]) * inv[0]
    uy = (py - lo[1]) * inv[1]
    uz = (pz - lo[2]) * inv[2]
    cx = np.int64(np.floor(ux))
    cy = np.int64(np.floor(uy))
    cz = np.int64(np.floor(uz))
    if cx < 0 or cy < 0 or cz < 0 or cx >= g or cy >= g or cz >= g:
        return cx, cy, cz, ux, uy, uz, -1
    v = np.int64(coarse[cx >> cs, cy >> cs, cz >> cs])
    if v == MIXED:
        v = np.int64(levels[cx, cy, cz])
    return cx, cy, cz, ux, uy, uz, v


@nb.njit(inline="always")
def _skip(k, t, cx, cy, cz, ux, uy, uz, lev, dx, dy, dz, inv, t0, t1, jr, step):
    """The next lattice index to evaluate after the empty sample ``k - 1`` at ``t`` in cell
    ``c`` of empty level ``lev`` (see the module doc): ``k`` itself when the point is near a
    face of its cube or the cube ends within a step."""
    size = 1 << lev
    t_exit = np.float64(t1)
    for a in range(3):
        c = cx if a == 0 else (cy if a == 1 else cz)
        u = np.float64(ux if a == 0 else (uy if a == 1 else uz))
        v = np.float64(dx if a == 0 else (dy if a == 1 else dz)) * np.float64(inv[a])
        b0 = np.float64((c >> lev) << lev) + MARGIN
        b1 = b0 + size - 2.0 * MARGIN
        if not (b0 <= u <= b1):
            return k
        if v > 0.0:
            t_exit = min(t_exit, t + (b1 - u) / v)
        elif v < 0.0:
            t_exit = min(t_exit, t + (b0 - u) / v)
    n_steps = (t_exit - np.float64(t0)) / np.float64(step) - np.float64(jr)
    if not n_steps < 4e18:                       # an infinite t_max and a zero direction
        return k
    return max(k, np.int64(math.floor(n_steps)) - 1)


@nb.njit(parallel=True, cache=True, nogil=True)
def march_count(origins, dirs, t_min, t_max, jitter, k_start, step, levels, coarse, cs, lo,
                inv, max_per_ray, counts, k_next, done):  # pragma: no cover - compiled
    """Pass 1: ``counts[r]`` emitted samples, ``k_next[r]``, ``done[r]`` (see module doc;
    ``levels``: :func:`empty_levels` of the occupancy mask, ``coarse``: its
    :func:`coarse_levels` with cubes of ``2^cs`` cells)."""
    g = levels.shape[0]
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
            cx, cy, cz, ux, uy, uz, lev = _cell_level(ox + t * dx, oy + t * dy, oz + t * dz,
                                                      lo, inv, levels, coarse, cs, g)
            k += 1
            if lev == OCCUPIED:
                n += 1
                if max_per_ray > 0 and n >= max_per_ray:
                    break
            elif lev >= 0:
                k = _skip(k, t, cx, cy, cz, ux, uy, uz, lev, dx, dy, dz, inv, t0, t1, jr, step)
        counts[r] = n
        k_next[r] = k
        done[r] = not (t0 + (jr + np.float32(k)) * step < t1)


@nb.njit(parallel=True, cache=True, nogil=True)
def march_fill(origins, dirs, t_min, t_max, jitter, k_start, step, levels, coarse, cs, lo,
               inv, offsets, ray_idx, ts, pts):  # pragma: no cover - compiled
    """Pass 2: write the samples of ray ``r`` to rows ``offsets[r]:offsets[r+1]``."""
    g = levels.shape[0]
    for r in nb.prange(origins.shape[0]):
        ox, oy, oz = origins[r, 0], origins[r, 1], origins[r, 2]
        dx, dy, dz = dirs[r, 0], dirs[r, 1], dirs[r, 2]
        t0 = t_min[r]
        t1 = t_max[r]
        jr = jitter[r]
        k = k_start[r]
        i = offsets[r]
        end = offsets[r + 1]
        while i < end:
            t = t0 + (jr + np.float32(k)) * step
            px = ox + t * dx
            py = oy + t * dy
            pz = oz + t * dz
            cx, cy, cz, ux, uy, uz, lev = _cell_level(px, py, pz, lo, inv, levels, coarse, cs,
                                                      g)
            k += 1
            if lev == OCCUPIED:
                ray_idx[i] = r
                ts[i] = t
                pts[i, 0] = px
                pts[i, 1] = py
                pts[i, 2] = pz
                i += 1
            elif lev >= 0:
                k = _skip(k, t, cx, cy, cz, ux, uy, uz, lev, dx, dy, dz, inv, t0, t1, jr, step)
