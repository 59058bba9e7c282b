"""The numba CPU kernel of the octree renderer (imported lazily on first use; compiles once,
cached on disk).

Same semantics as the torch twin (:mod:`plenoctree.render._torch_impl`, read its docstring for
the algorithm). What makes it fast:

* Points are quantised to integer coordinates (``QUANT_BITS`` bits per axis), so the cell index
  at level ``l`` is one bit of each coordinate: the descent needs no floating point at all.
* The nodes along the current root-to-leaf path are kept on a small stack. When the ray leaves a
  leaf, the highest bit that differs between the old and the new integer point gives the
  deepest common ancestor; the descent restarts there instead of at the root (most exits cross
  into a sibling or a cousin, so ~1-2 levels instead of the full depth).
* Per ray: the direction, its tree-space version, its reciprocal and the SH/SG basis are
  computed once; leaves with σ ≤ 0 are skipped without touching their colour coefficients;
  early termination when T < stop_thresh.
* Rays are processed in tiles of neighbouring pixels (cache-friendly) with dynamic scheduling
  over the tiles (``numba.set_parallel_chunksize``), so both cores stay busy when one half of
  the image is empty.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit, prange

from plenoctree import sh as _sh
from plenoctree.render.options import KIND_RGBA, KIND_SG, KIND_SH, QUANT_BITS, FormatInfo, RenderOptions

__all__ = ["render_rays_numba", "TILE", "CHUNK_TILES"]

TILE = 64          # rays per work item (consecutive pixels share nodes and leaves in cache)
CHUNK_TILES = 4    # work items per dynamic-scheduling chunk
_SCALE = float(2 ** QUANT_BITS)
_BIG = 1e30
_Z32 = np.float32(0.0)
_ONE32 = np.float32(1.0)
_INV_SCALE = 1.0 / _SCALE

_C0 = _sh.SH_C0
_C1 = _sh.SH_C1
_C20, _C21, _C22, _C23, _C24 = _sh.SH_C2
_C30, _C31, _C32, _C33, _C34, _C35, _C36 = _sh.SH_C3
_C40, _C41, _C42, _C43, _C44, _C45, _C46, _C47, _C48 = _sh.SH_C4


@njit(cache=True, fastmath=True, inline="always")
def _basis(kind, n_b, x, y, z, sg, out):
    """Write the ``n_b`` basis values at unit direction (x, y, z) into ``out[:n_b]``."""
    if kind == KIND_SG:
        for b in range(n_b):
            cos = sg[b, 1] * x + sg[b, 2] * y + sg[b, 3] * z
            out[b] = math.exp(sg[b, 0] * (cos - 1.0)) / n_b
        return
    out[0] = _C0 if kind == KIND_SH else 1.0
    if n_b > 1:
        out[1] = -_C1 * y
        out[2] = _C1 * z
        out[3] = -_C1 * x
    if n_b > 4:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        out[4] = _C20 * xy
        out[5] = _C21 * yz
        out[6] = _C22 * (2.0 * zz - xx - yy)
        out[7] = _C23 * xz
        out[8] = _C24 * (xx - yy)
        if n_b > 9:
            out[9] = _C30 * y * (3.0 * xx - yy)
            out[10] = _C31 * xy * z
            out[11] = _C32 * y * (4.0 * zz - xx - yy)
            out[12] = _C33 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
            out[13] = _C34 * x * (4.0 * zz - xx - yy)
            out[14] = _C35 * z * (xx - yy)
            out[15] = _C36 * x * (xx - 3.0 * yy)
        if n_b > 16:
            out[16] = _C40 * xy * (xx - yy)
            out[17] = _C41 * yz * (3.0 * xx - yy)
            out[18] = _C42 * xy * (7.0 * zz - 1.0)
            out[19] = _C43 * yz * (7.0 * zz - 3.0)
            out[20] = _C44 * (zz * (35.0 * zz - 30.0) + 3.0)
            out[21] = _C45 * xz * (7.0 * zz - 3.0)
            out[22] = _C46 * (xx - yy) * (7.0 * zz - 1.0)
            out[23] = _C47 * xz * (xx - 3.0 * yy)
            out[24] = _C48 * (xx * (xx - 3.0 * yy) - yy * (3.0 * xx - yy))


@njit(cache=True, fastmath=True, inline="always")
def _render_one(child, data, offset, invr, ox, oy, oz, dx, dy, dz, kind, n_b, sg, b_lo, b_hi,
                stop, eps, use_stack, basis, stack, out3):
    """March one ray; returns (T, Σw, Σw t_mid) and writes Σ w c into ``out3``."""
    out3[0] = 0.0
    out3[1] = 0.0
    out3[2] = 0.0
    norm = math.sqrt(dx * dx + dy * dy + dz * dz)
    dx /= norm
    dy /= norm
    dz /= norm
    # Tree-space ray p(t) = o' + t d', t in world units.
    px = offset[0] + invr[0] * ox
    py = offset[1] + invr[1] * oy
    pz = offset[2] + invr[2] * oz
    vx = invr[0] * dx
    vy = invr[1] * dy
    vz = invr[2] * dz
    # Box [0, 1]^3.
    t0 = 0.0
    t1 = _BIG
    for a in range(3):
        p = px if a == 0 else (py if a == 1 else pz)
        v = vx if a == 0 else (vy if a == 1 else vz)
        if v == 0.0:
            if p < 0.0 or p > 1.0:
                t1 = -_BIG
        else:
            ta = (0.0 - p) / v
            tb = (1.0 - p) / v
            if ta > tb:
                ta, tb = tb, ta
            t0 = max(t0, ta)
            t1 = min(t1, tb)
    if not t0 < t1:
        return 1.0, 0.0, 0.0
    ix_ = 1.0 / vx if vx != 0.0 else _BIG
    iy_ = 1.0 / vy if vy != 0.0 else _BIG
    iz_ = 1.0 / vz if vz != 0.0 else _BIG
    eps_t = eps / math.sqrt(vx * vx + vy * vy + vz * vz)
    sx = 1 if vx >= 0.0 else 0
    sy = 1 if vy >= 0.0 else 0
    sz = 1 if vz >= 0.0 else 0

    _basis(kind, n_b, dx, dy, dz, sg, basis)
    for b in range(n_b):
        if b < b_lo or b > b_hi:
            basis[b] = 0.0

    dim = data.shape[1]
    trans = 1.0
    w_sum = 0.0
    wt_sum = 0.0
    t = t0
    level = 0
    stack[0] = 0
    qx_prev = -1
    qy_prev = 0
    qz_prev = 0
    top = QUANT_BITS - 1
    while t < t1:
        ts = t + eps_t
        # Clamp first, then truncate (= floor for non-negative values).
        qx = int(min(max((px + ts * vx) * _SCALE, 0.0), _SCALE - 1.0))
        qy = int(min(max((py + ts * vy) * _SCALE, 0.0), _SCALE - 1.0))
        qz = int(min(max((pz + ts * vz) * _SCALE, 0.0), _SCALE - 1.0))
        if use_stack and qx_prev >= 0:
            # Deepest level whose node is shared with the previous path.
            diff = (qx ^ qx_prev) | (qy ^ qy_prev) | (qz ^ qz_prev)
            while level > 0 and (diff >> (QUANT_BITS - level)) != 0:
                level -= 1
        else:
            level = 0
        node = stack[level]
        while True:
            sh = top - level
            cell = node * 8 + (((qx >> sh) & 1) << 2) + (((qy >> sh) & 1) << 1) + ((qz >> sh) & 1)
            c = child[cell]
            if c == 0:
                break
            node += c
            level += 1
            stack[level] = node
        qx_prev = qx
        qy_prev = qy
        qz_prev = qz
        sh = top - level
        # Exit face of the leaf: its low (s = 0) or high (s = 1) side per axis.
        bx = (((qx >> sh) + sx) << sh) * _INV_SCALE
        by = (((qy >> sh) + sy) << sh) * _INV_SCALE
        bz = (((qz >> sh) + sz) << sh) * _INV_SCALE
        tx = (bx - px) * ix_
        ty = (by - py) * iy_
        tz = (bz - pz) * iz_
        t_end = min(max(min(tx, min(ty, tz)), ts), t1)
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
                   stop, eps, use_stack, tile_size, rgb, depth, alpha):
    n = origins.shape[0]
    n_tiles = (n + tile_size - 1) // tile_size
    for tile in prange(n_tiles):
        basis = np.zeros(max(25, n_b), dtype=np.float32)
        stack = np.zeros(QUANT_BITS + 1, dtype=np.int64)
        acc = np.zeros(3, dtype=np.float64)
        for i in range(tile * tile_size, min(n, (tile + 1) * tile_size)):
            trans, w_sum, wt_sum = _render_one(
                child, data, offset, invr, origins[i, 0], origins[i, 1], origins[i, 2],
                dirs[i, 0], dirs[i, 1], dirs[i, 2], kind, n_b, sg, b_lo, b_hi, stop, eps,
                use_stack, basis, stack, acc)
            for ch in range(3):
                rgb[i, ch] = acc[ch] + trans * bg[ch]
            depth[i] = wt_sum / max(w_sum, 1e-10)
            alpha[i] = 1.0 - trans


def render_rays_numba(child: np.ndarray, data: np.ndarray, offset: np.ndarray,
                      invradius: np.ndarray, info: FormatInfo, extra_data: np.ndarray | None,
                      origins: np.ndarray, dirs: np.ndarray, options: RenderOptions,
                      use_stack: bool = True, tile: int = TILE, chunk_tiles: int = CHUNK_TILES
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render ``[N, 3]`` rays with the numba kernel; returns float32 ``rgb [N,3], depth [N],
    alpha [N]`` (numpy).

    ``child`` int32 ``[n_nodes, 2, 2, 2]``, ``data`` ``[n_nodes, 2, 2, 2, D]`` (converted to
    float32 contiguous if needed; float32 trees are used in place), geometry in float64 inside
    the kernel. ``use_stack=False`` re-descends from the root at every step (the baseline the
    benchmark compares against); ``tile`` rays form one work item and ``chunk_tiles`` items one
    dynamic-scheduling chunk.
    """
    n_nodes = child.shape[0]
    child_flat = np.ascontiguousarray(child, dtype=np.int32).reshape(n_nodes * 8)
    data2 = np.ascontiguousarray(data, dtype=np.float32).reshape(n_nodes * 8, data.shape[-1])
    off = np.ascontiguousarray(offset, dtype=np.float64).reshape(3)
    inv = np.ascontiguousarray(invradius, dtype=np.float64).reshape(3)
    o = np.ascontiguousarray(origins, dtype=np.float32).reshape(-1, 3)
    d = np.ascontiguousarray(dirs, dtype=np.float32).reshape(-1, 3)
    if extra_data is not None and info.kind == KIND_SG:
        sg = np.ascontiguousarray(extra_data, dtype=np.float64).reshape(info.basis_dim, 4)
    else:
        sg = np.zeros((1, 4), dtype=np.float64)
    b_lo, b_hi = options.basis_range(info.basis_dim)
    bg = np.asarray(options.background, dtype=np.float64)
    n = o.shape[0]
    rgb = np.empty((n, 3), dtype=np.float32)
    depth = np.empty(n, dtype=np.float32)
    alpha = np.empty(n, dtype=np.float32)
    if n == 0:
        return rgb, depth, alpha
    old = numba.get_parallel_chunksize()
    numba.set_parallel_chunksize(max(1, int(chunk_tiles)))
    try:
        _render_kernel(child_flat, data2, off, inv, o, d, info.kind, info.basis_dim, sg, b_lo,
                       b_hi, bg, float(options.stop_thresh), float(options.step_eps),
                       bool(use_stack), max(1, int(tile)), rgb, depth, alpha)
    finally:
        numba.set_parallel_chunksize(old)
    return rgb, depth, alpha
