"""Numba kernel of the visibility filter: maximum ray weight per grid cell (lazy import).

Same semantics as the torch twin :func:`plenoctree.convert.visibility._max_weights_torch`
(the spec). Each ray (unit direction) is clipped to the grid box (from ``t = 0``) and walked
cell by cell with a 3-D DDA (Amanatides & Woo): the segment in cell ``c`` between two
consecutive boundary crossings has world length δ, weight ``w = T (1 - exp(-σ_c δ))``, and
``T *= exp(-σ_c δ)``. The ray stops once ``T < min_weight`` (later weights are smaller than
``min_weight`` anyway) or when it leaves the box. Arithmetic is float64.

Only *candidate* cells (``index[c] >= 0``) record weights, into row ``thread id`` of
``out [n_threads, M]`` — every thread owns its row, so the parallel loop has no races and the
caller reduces ``out.max(0)``. Rays are split into tiles of ``TILE`` that the threads take one
at a time from a shared counter (:mod:`plenoctree.render._schedule_numba`: numba's ``prange``
alone is a static split, and a view's rays cost most where the object is); the maximum does not
depend on which thread took a tile, so the result is the same with any schedule.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit, prange

from ..render._schedule_numba import next_item

__all__ = ["max_weights_numba", "TILE"]

TILE = 64


@njit(cache=True, inline="always")
def _start(o, d, lo, cell, res, t0):
    """Starting cell, step, first crossing and crossing spacing along one axis."""
    p = (o + t0 * d - lo) / cell
    if d > 0.0:
        c = min(max(int(math.floor(p)), 0), res - 1)
        return c, 1, (lo + (c + 1) * cell - o) / d, cell / d
    if d < 0.0:
        c = min(max(int(math.ceil(p)) - 1, 0), res - 1)
        return c, -1, (lo + c * cell - o) / d, -cell / d
    c = min(max(int(math.floor(p)), 0), res - 1)
    return c, 0, 1e300, 1e300


@njit(cache=True, inline="always")
def _slab(o, d, lo, hi, t0, t1):
    """Clip ``[t0, t1]`` to the slab ``[lo, hi]`` of one axis (empty: t1 < t0)."""
    if d == 0.0:
        if o < lo or o > hi:
            return 1.0, 0.0
        return t0, t1
    ta = (lo - o) / d
    tb = (hi - o) / d
    if ta > tb:
        ta, tb = tb, ta
    return max(t0, ta), min(t1, tb)


@njit(cache=True)
def _march(sigma, index, lo, cell, ox, oy, oz, dx, dy, dz, min_weight, row):
    """Walk one ray through the grid, updating ``row`` (see the module docstring)."""
    res = sigma.shape[0]
    norm = math.sqrt(dx * dx + dy * dy + dz * dz)
    if not norm > 0.0:
        return
    dx /= norm
    dy /= norm
    dz /= norm
    t0, t1 = _slab(ox, dx, lo[0], lo[0] + cell[0] * res, 0.0, 1e300)
    t0, t1 = _slab(oy, dy, lo[1], lo[1] + cell[1] * res, t0, t1)
    t0, t1 = _slab(oz, dz, lo[2], lo[2] + cell[2] * res, t0, t1)
    if not t1 > t0:
        return
    i, si, ti, di = _start(ox, dx, lo[0], cell[0], res, t0)
    j, sj, tj, dj = _start(oy, dy, lo[1], cell[1], res, t0)
    k, sk, tk, dk = _start(oz, dz, lo[2], cell[2], res, t0)
    t = t0
    trans = 1.0
    while True:
        # the axis whose boundary comes first (x before y before z on ties)
        if ti <= tj and ti <= tk:
            te = ti
            axis = 0
        elif tj <= tk:
            te = tj
            axis = 1
        else:
            te = tk
            axis = 2
        if te > t1:
            te = t1
        delta = te - t
        if delta > 0.0:
            s = sigma[i, j, k]
            if s > 0.0:
                att = math.exp(-s * delta)
                w = trans * (1.0 - att)
                c = index[i, j, k]
                if c >= 0 and w > row[c]:
                    row[c] = w
                trans *= att
                if trans < min_weight:
                    return
            t = te
        if te >= t1:
            return
        if axis == 0:
            i += si
            if i < 0 or i >= res:
                return
            ti += di
        elif axis == 1:
            j += sj
            if j < 0 or j >= res:
                return
            tj += dj
        else:
            k += sk
            if k < 0 or k >= res:
                return
            tk += dk


@njit(cache=True, parallel=True)
def _kernel(sigma, index, lo, cell, origins, dirs, min_weight, out, threads):
    n = origins.shape[0]
    n_tiles = (n + TILE - 1) // TILE
    counter = np.zeros(1, np.int64)
    for _ in prange(max(1, min(threads, n_tiles))):
        row = out[numba.get_thread_id()]
        while True:
            tile = next_item(counter)
            if tile >= n_tiles:
                break
            for r in range(tile * TILE, min(n, (tile + 1) * TILE)):
                _march(sigma, index, lo, cell, np.float64(origins[r, 0]),
                       np.float64(origins[r, 1]), np.float64(origins[r, 2]),
                       np.float64(dirs[r, 0]), np.float64(dirs[r, 1]), np.float64(dirs[r, 2]),
                       min_weight, row)


def max_weights_numba(sigma: np.ndarray, index: np.ndarray, lo: np.ndarray, cell: np.ndarray,
                      origins: np.ndarray, dirs: np.ndarray, min_weight: float,
                      out: np.ndarray) -> None:
    """Accumulate per-thread maximum ray weights of candidate cells into ``out`` in place.

    Args:
        sigma: float32 ``[R, R, R]`` σ per cell (1 / world length).
        index: int32 ``[R, R, R]``: column of ``out`` for candidate cells, -1 otherwise.
        lo, cell: float64 ``[3]`` world corner of the grid and cell sides.
        origins, dirs: float32 ``[N, 3]`` rays (directions of any non-zero length).
        min_weight: stop a ray once its transmittance is below this.
        out: float32 ``[n_threads, M]`` running maxima (``n_threads >= numba.get_num_threads()``).
    """
    if out.shape[0] < numba.get_num_threads():
        raise ValueError(f"out needs {numba.get_num_threads()} rows, got {out.shape[0]}")
    _kernel(sigma, index, np.ascontiguousarray(lo, np.float64),
            np.ascontiguousarray(cell, np.float64), np.ascontiguousarray(origins, np.float32),
            np.ascontiguousarray(dirs, np.float32), float(min_weight), out,
            numba.get_num_threads())
