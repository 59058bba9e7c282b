"""The numba CPU kernel of the octree renderer (imported lazily on first use; compiles once,
cached on disk), and its per-ray counters.

Same semantics as the torch twin (:mod:`plenoctree.render._torch_impl`, the spec); the
traversal is :mod:`._march_numba`'s, shared with the fine-tuning kernels. Per ray: the
direction, its tree-space version, its reciprocal and the SH/SG basis are computed once;
leaves with σ ≤ 0 are skipped without touching their colour coefficients; early termination
when T < stop_thresh. Rays of an image are processed in 8×8-pixel tiles (neighbouring rays share
nodes and leaves in cache) with dynamic scheduling over the tiles
(``numba.set_parallel_chunksize``), so both cores stay busy when one half of the image is
empty.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
from numba import njit, prange

from ._march_numba import (MAX_LEVEL, MAX_STEPS, STACK_SIZE, basis_values, next_leaf,
                           ray_start)
from .options import KIND_RGBA, KIND_SG, FormatInfo, RenderOptions

__all__ = ["render_rays_numba", "ray_stats_numba", "Prepared", "prepare", "render_prepared",
           "empty_outputs", "TILE", "TILE_2D", "CHUNK_TILES", "STAT_NAMES"]

TILE = 64          # rays per work item when the image width is unknown (one row of rays)
TILE_2D = (8, 8)   # pixels per work item of an image (1.2x faster than 64x1 rows on lego)
CHUNK_TILES = 4    # work items per dynamic-scheduling chunk

_Z32 = np.float32(0.0)
_ONE32 = np.float32(1.0)

#: Columns of :func:`ray_stats_numba`'s output, per ray.
STAT_NAMES = ("leaves", "sigma_leaves", "negligible", "descent", "hit", "stopped")
NEGLIGIBLE_WEIGHT = 1e-4   # a σ > 0 segment with w = T (1 - e^{-σδ}) below this is "negligible"


@njit(cache=True, fastmath=True, inline="always")
def _render_one(child, data, offset, invr, ox, oy, oz, dx, dy, dz, kind, n_b, sg, b_lo, b_hi,
                stop, eps, use_stack, max_level, max_steps, basis, st, stack, out3):
    """March one ray (at most ``max_steps`` segments); returns (T, Σw, Σw t_mid) and writes
    Σ w c into ``out3``."""
    out3[0] = 0.0
    out3[1] = 0.0
    out3[2] = 0.0
    dx, dy, dz, px, py, pz, vx, vy, vz, ix, iy, iz, t0, t1, eps_t = ray_start(
        offset, invr, ox, oy, oz, dx, dy, dz, eps)
    if not t0 < t1:
        return 1.0, 0.0, 0.0
    basis_values(kind, n_b, dx, dy, dz, sg, b_lo, b_hi, basis)
    dim = data.shape[1]
    trans = 1.0
    w_sum = 0.0
    wt_sum = 0.0
    t = t0
    st[0] = 0
    st[1] = -1
    stack[0] = 0
    steps = 0
    while t < t1 and steps < max_steps:
        steps += 1
        cell, t_end, _ = next_leaf(child, px, py, pz, vx, vy, vz, ix, iy, iz, t, eps_t, t1,
                                   use_stack, max_level, st, stack)
        sigma = data[cell, dim - 1]
        if sigma > 0.0:
            att = math.exp(-sigma * (t_end - t))
            w = trans * (1.0 - att)
            # Colour in float32 (vectorisable dot products, single-precision exp).
            if kind == KIND_RGBA:
                ar = data[cell, 0] * basis[0]       # basis[0] = 1, or 0 if excluded
                ag = data[cell, 1] * basis[0]
                ab = data[cell, 2] * basis[0]
            else:
                ar = _Z32
                ag = _Z32
                ab = _Z32
                for b in range(n_b):          # basis is 0 outside [b_lo, b_hi]
                    yb = basis[b]
                    ar += data[cell, b] * yb
                    ag += data[cell, n_b + b] * yb
                    ab += data[cell, 2 * n_b + b] * yb
            out3[0] += w / (_ONE32 + math.exp(-ar))
            out3[1] += w / (_ONE32 + math.exp(-ag))
            out3[2] += w / (_ONE32 + math.exp(-ab))
            w_sum += w
            wt_sum += w * 0.5 * (t + t_end)
            trans *= att
            if trans < stop:
                break
        t = t_end
    return trans, w_sum, wt_sum


@njit(parallel=True, cache=True, fastmath=True)
def _render_kernel(child, data, offset, invr, origins, dirs, kind, n_b, sg, b_lo, b_hi, bg,
                   stop, eps, use_stack, max_level, max_steps, width, tile_w, tile_h, rgb, depth,
                   alpha):
    """Rays ``i = y * width + x`` in tiles of ``tile_w × tile_h`` pixels (one work item each)."""
    n = origins.shape[0]
    height = (n + width - 1) // width
    ntx = (width + tile_w - 1) // tile_w
    nty = (height + tile_h - 1) // tile_h
    for tile in prange(ntx * nty):
        ty = tile // ntx
        tx = tile - ty * ntx
        basis = np.zeros(max(25, n_b), dtype=np.float32)
        st = np.zeros(4, dtype=np.int64)
        stack = np.zeros(STACK_SIZE, dtype=np.int64)
        acc = np.zeros(3, dtype=np.float64)
        for y in range(ty * tile_h, min(height, (ty + 1) * tile_h)):
            for x in range(tx * tile_w, min(width, (tx + 1) * tile_w)):
                i = y * width + x
                if i >= n:
                    break
                trans, w_sum, wt_sum = _render_one(
                    child, data, offset, invr, origins[i, 0], origins[i, 1], origins[i, 2],
                    dirs[i, 0], dirs[i, 1], dirs[i, 2], kind, n_b, sg, b_lo, b_hi, stop, eps,
                    use_stack, max_level, max_steps, basis, st, stack, acc)
                for ch in range(3):
                    rgb[i, ch] = acc[ch] + trans * bg[ch]
                depth[i] = wt_sum / max(w_sum, 1e-10)
                alpha[i] = 1.0 - trans


@njit(parallel=True, cache=True, fastmath=True)
def _stats_kernel(child, data, offset, invr, origins, dirs, stop, eps, negligible, max_level,
                  max_steps, out):
    """Per-ray counters of the renderer's march (same segments, same early stop): ``out [N, 6]``
    int64 columns :data:`STAT_NAMES`."""
    n = origins.shape[0]
    dim = data.shape[1]
    for i in prange(n):
        st = np.zeros(4, dtype=np.int64)
        stack = np.zeros(STACK_SIZE, dtype=np.int64)
        for k in range(6):
            out[i, k] = 0
        dx, dy, dz, px, py, pz, vx, vy, vz, ix, iy, iz, t0, t1, eps_t = ray_start(
            offset, invr, origins[i, 0], origins[i, 1], origins[i, 2], dirs[i, 0], dirs[i, 1],
            dirs[i, 2], eps)
        if not t0 < t1:
            continue
        out[i, 4] = 1
        trans = 1.0
        t = t0
        st[1] = -1
        while t < t1 and out[i, 0] < max_steps:
            cell, t_end, n_desc = next_leaf(child, px, py, pz, vx, vy, vz, ix, iy, iz, t, eps_t,
                                            t1, True, max_level, st, stack)
            out[i, 0] += 1
            out[i, 3] += n_desc
            sigma = data[cell, dim - 1]
            if sigma > 0.0:
                att = math.exp(-sigma * (t_end - t))
                out[i, 1] += 1
                if trans * (1.0 - att) < negligible:
                    out[i, 2] += 1
                trans *= att
                if trans < stop:
                    out[i, 5] = 1
                    break
            t = t_end


def _flat(child: np.ndarray, data: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n_nodes = child.shape[0]
    child_flat = np.ascontiguousarray(child, dtype=np.int32).reshape(n_nodes * 8)
    data2 = np.ascontiguousarray(data, dtype=np.float32).reshape(n_nodes * 8, data.shape[-1])
    return child_flat, data2


def _vec(x: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(x, dtype=np.float64).reshape(3)


@dataclass
class Prepared:
    """The kernel's arguments for one tree and one set of options (see :func:`prepare`)."""

    child: np.ndarray          # int32 [n_cells]
    data: np.ndarray           # float32 [n_cells, D]
    offset: np.ndarray         # float64 [3]
    invr: np.ndarray           # float64 [3]
    kind: int
    n_b: int
    sg: np.ndarray             # float64 [B, 4] (SG) or [1, 4]
    b_lo: int
    b_hi: int
    bg: np.ndarray             # float64 [3]
    stop: float
    eps: float
    max_steps: int             # segments per ray at most (octree.limits.max_steps)


def prepare(tree: Any, info: FormatInfo, options: RenderOptions) -> Prepared:
    """Pack ``tree`` (child, data, box, extra_data) and ``options`` for :func:`render_prepared`."""
    return _prepare(tree.child, tree.data, tree.offset, tree.invradius, info,
                    getattr(tree, "extra_data", None), options)


def _prepare(child, data, offset, invradius, info, extra_data, options) -> Prepared:
    child_flat, data2 = _flat(child, data)
    if extra_data is not None and info.kind == KIND_SG:
        sg = np.ascontiguousarray(extra_data, dtype=np.float64).reshape(info.basis_dim, 4)
    else:
        sg = np.zeros((1, 4), dtype=np.float64)
    b_lo, b_hi = options.basis_range(info.basis_dim)
    return Prepared(child_flat, data2, _vec(offset), _vec(invradius), info.kind, info.basis_dim,
                    sg, b_lo, b_hi, np.asarray(options.background, dtype=np.float64),
                    float(options.stop_thresh), float(options.step_eps), MAX_STEPS)


def empty_outputs(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Uninitialised float32 ``rgb [n, 3], depth [n], alpha [n]``."""
    return (np.empty((n, 3), dtype=np.float32), np.empty(n, dtype=np.float32),
            np.empty(n, dtype=np.float32))


def render_prepared(p: Prepared, origins: np.ndarray, dirs: np.ndarray,
                    out: tuple[np.ndarray, np.ndarray, np.ndarray], use_stack: bool = True,
                    width: int = 0, tile: tuple[int, int] | None = None,
                    chunk_tiles: int = CHUNK_TILES) -> None:
    """Render float32 contiguous ``origins, dirs [N, 3]`` into ``out = (rgb, depth, alpha)``.

    ``width > 0``: the rays are the pixels of an image ``width`` wide (row-major) and are
    marched in ``tile = (w, h)`` pixel tiles (default :data:`TILE_2D`: neighbouring rays share
    nodes and leaves in cache, also across rows); ``width = 0``: one row (``(TILE, 1)``)."""
    rgb, depth, alpha = out
    if origins.shape[0] == 0:
        return
    old = numba.get_parallel_chunksize()
    numba.set_parallel_chunksize(max(1, int(chunk_tiles)))
    try:
        n = origins.shape[0]
        if width <= 0 or width > n:
            width, tw, th = n, TILE, 1
        else:
            tw, th = tile if tile is not None else TILE_2D
        _render_kernel(p.child, p.data, p.offset, p.invr, origins, dirs, p.kind, p.n_b, p.sg,
                       p.b_lo, p.b_hi, p.bg, p.stop, p.eps, bool(use_stack), MAX_LEVEL,
                       p.max_steps, int(width), max(1, int(tw)), max(1, int(th)), rgb, depth,
                       alpha)
    finally:
        numba.set_parallel_chunksize(old)


def render_rays_numba(child: np.ndarray, data: np.ndarray, offset: np.ndarray,
                      invradius: np.ndarray, info: FormatInfo, extra_data: np.ndarray | None,
                      origins: np.ndarray, dirs: np.ndarray, options: RenderOptions,
                      use_stack: bool = True, width: int = 0,
                      tile: tuple[int, int] | None = None, chunk_tiles: int = CHUNK_TILES
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render ``[N, 3]`` rays with the numba kernel; returns float32 ``rgb [N,3], depth [N],
    alpha [N]`` (numpy).

    ``child`` int32 ``[n_nodes, 2, 2, 2]``, ``data`` ``[n_nodes, 2, 2, 2, D]`` (converted to
    float32 contiguous if needed; float32 trees are used in place), geometry in float64 inside
    the kernel. ``use_stack=False`` re-descends from the root at every step (the reference the
    tests compare the ancestor stack against); ``width``/``tile``: see :func:`render_prepared`;
    ``chunk_tiles`` work items form one dynamic-scheduling chunk.
    """
    p = _prepare(child, data, offset, invradius, info, extra_data, options)
    o = np.ascontiguousarray(origins, dtype=np.float32).reshape(-1, 3)
    d = np.ascontiguousarray(dirs, dtype=np.float32).reshape(-1, 3)
    out = empty_outputs(o.shape[0])
    render_prepared(p, o, d, out, use_stack, width, tile, chunk_tiles)
    return out


def ray_stats_numba(child: np.ndarray, data: np.ndarray, offset: np.ndarray,
                    invradius: np.ndarray, origins: np.ndarray, dirs: np.ndarray,
                    options: RenderOptions, negligible: float = NEGLIGIBLE_WEIGHT) -> np.ndarray:
    """Per-ray counters of the render march, int64 ``[N, 6]``, columns :data:`STAT_NAMES`:
    leaves visited (segments), leaves with σ > 0, σ > 0 segments of weight < ``negligible``,
    ``child`` reads of the descents, hit the box (0/1), stopped early at ``T < stop_thresh``
    (0/1). For benchmarks: where a real ray's time goes."""
    child_flat, data2 = _flat(child, data)
    o = np.ascontiguousarray(origins, dtype=np.float32).reshape(-1, 3)
    d = np.ascontiguousarray(dirs, dtype=np.float32).reshape(-1, 3)
    out = np.zeros((o.shape[0], len(STAT_NAMES)), dtype=np.int64)
    if o.shape[0]:
        _stats_kernel(child_flat, data2, _vec(offset), _vec(invradius), o, d,
                      float(options.stop_thresh), float(options.step_eps), float(negligible),
                      MAX_LEVEL, MAX_STEPS, out)
    return out
