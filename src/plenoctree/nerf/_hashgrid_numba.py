"""numba kernels of the multiresolution grid encoding (forward and table gradient).

Imported lazily by :mod:`plenoctree.nerf.encoding` the first time the numba backend runs;
``cache=True`` keeps the compiled code on disk. The pure-torch twin
:func:`plenoctree.nerf.encoding._hashgrid_encode_torch` is the specification; both compute,
for every point ``x`` in the unit cube and every level ``l`` of resolution ``r_l``::

    p = x * r_l;  i = clamp(floor(p), 0, r_l - 1);  f = p - i
    out[n, l*F:(l+1)*F] = Σ_{c ∈ {0,1}^3} Π_a (c_a ? f_a : 1 - f_a) · table[off_l + idx_l(i + c)]

with ``idx_l`` the dense index ``u + v (r+1) + w (r+1)^2`` of the ``(r+1)^3`` vertices, or, for
hashed levels, ``(u ^ v·2654435761 ^ w·805459861) & (size_l - 1)`` (size a power of two).

Both kernels are level-major: each thread handles whole levels for all points, so one level's
table slice (≤ 2 MB by default) stays in that core's cache during the pass (3x faster than
looping over levels per point), no two threads write the same table row in the backward pass,
and results do not depend on the thread count. The levels' features and gradients live in
per-level ``[N, F]`` slices while a level is processed, and are swapped to and from the
network's ``[N, L * F]`` layout in one blocked pass.
"""

from __future__ import annotations

import numba as nb
import numpy as np

_P1 = np.uint32(2654435761)
_P2 = np.uint32(805459861)
_BLOCK = 1024   # points per work item of the layout swap


@nb.njit(inline="always")
def _cell(xa, r, rf):
    """Cell ``i = clamp(floor(p), 0, r - 1)`` and fraction ``p - i`` of ``p = xa * r``
    (truncation equals floor here: a negative ``p`` clamps to cell 0 either way; min / max
    compile to conditional moves, no branches)."""
    p = xa * rf
    i = min(max(np.int64(p), 0), r - 1)
    return i, p - np.float32(i)


@nb.njit(inline="always")
def _corners(x, n, r, off, size, hsh):
    """The 8 table rows and trilinear weights of point ``n`` at one level.

    Corner order: bit 0 = x, bit 1 = y, bit 2 = z (row ``r000, r100, r010, r110, r001, …``).
    """
    rf = np.float32(r)
    i0, f0 = _cell(x[n, 0], r, rf)
    i1, f1 = _cell(x[n, 1], r, rf)
    i2, f2 = _cell(x[n, 2], r, rf)
    one = np.float32(1.0)
    g0, g1, g2 = one - f0, one - f1, one - f2
    w00, w10, w01, w11 = g0 * g1, f0 * g1, g0 * f1, f0 * f1
    if hsh:
        # in uint32: the masked low bits of the products do not depend on the wider bits
        m = np.uint32(size - 1)
        a0, a1 = np.uint32(i0), np.uint32(i0 + 1)
        b0, b1 = np.uint32(i1) * _P1, np.uint32(i1 + 1) * _P1
        c0, c1 = np.uint32(i2) * _P2, np.uint32(i2 + 1) * _P2
        rows = (off + np.int64((a0 ^ b0 ^ c0) & m), off + np.int64((a1 ^ b0 ^ c0) & m),
                off + np.int64((a0 ^ b1 ^ c0) & m), off + np.int64((a1 ^ b1 ^ c0) & m),
                off + np.int64((a0 ^ b0 ^ c1) & m), off + np.int64((a1 ^ b0 ^ c1) & m),
                off + np.int64((a0 ^ b1 ^ c1) & m), off + np.int64((a1 ^ b1 ^ c1) & m))
    else:
        r1 = r + 1
        sz = r1 * r1
        base = off + i0 + i1 * r1 + i2 * sz
        rows = (base, base + 1, base + r1, base + r1 + 1,
                base + sz, base + sz + 1, base + r1 + sz, base + r1 + sz + 1)
    ws = (w00 * g2, w10 * g2, w01 * g2, w11 * g2, w00 * f2, w10 * f2, w01 * f2, w11 * f2)
    return rows, ws


@nb.njit(parallel=True, fastmath=True, cache=True, nogil=True)
def _forward_levels(x, table, res, offsets, hashed, order, out):  # pragma: no cover - compiled
    """Encode points level by level into ``out`` float32 ``[L, N, F]`` (levels in ``order``)."""
    n_pts = x.shape[0]
    nf = table.shape[1]
    for k in nb.prange(order.shape[0]):
        lev = order[k]
        r = res[lev]
        off = offsets[lev]
        size = offsets[lev + 1] - off
        hsh = hashed[lev]
        for n in range(n_pts):
            rows, ws = _corners(x, n, r, off, size, hsh)
            if nf == 2:  # the default: both features of a row share a cache line
                a0 = np.float32(0.0)
                a1 = np.float32(0.0)
                for c in range(8):
                    a0 += ws[c] * table[rows[c], 0]
                    a1 += ws[c] * table[rows[c], 1]
                out[lev, n, 0] = a0
                out[lev, n, 1] = a1
                continue
            for f in range(nf):
                out[lev, n, f] = (ws[0] * table[rows[0], f] + ws[1] * table[rows[1], f]
                                  + ws[2] * table[rows[2], f] + ws[3] * table[rows[3], f]
                                  + ws[4] * table[rows[4], f] + ws[5] * table[rows[5], f]
                                  + ws[6] * table[rows[6], f] + ws[7] * table[rows[7], f])


@nb.njit(parallel=True, fastmath=True, cache=True, nogil=True)
def _backward_levels(x, grad_lnf, res, offsets, hashed, order, grad_table):  # pragma: no cover
    """Add the table gradient of ``grad_lnf`` float32 ``[L, N, F]`` into ``grad_table``."""
    n_pts = x.shape[0]
    nf = grad_table.shape[1]
    for k in nb.prange(order.shape[0]):
        lev = order[k]
        r = res[lev]
        off = offsets[lev]
        size = offsets[lev + 1] - off
        hsh = hashed[lev]
        for n in range(n_pts):
            rows, ws = _corners(x, n, r, off, size, hsh)
            if nf == 2:
                g0 = grad_lnf[lev, n, 0]
                g1 = grad_lnf[lev, n, 1]
                for c in range(8):
                    grad_table[rows[c], 0] += ws[c] * g0
                    grad_table[rows[c], 1] += ws[c] * g1
                continue
            for f in range(nf):
                g = grad_lnf[lev, n, f]
                for c in range(8):
                    grad_table[rows[c], f] += ws[c] * g


@nb.njit(parallel=True, cache=True, nogil=True)
def _swap_axes(lnf, flat, to_flat):  # pragma: no cover - compiled
    """Copy ``lnf [L, N, F]`` into ``flat [N, L * F]`` (``to_flat``) or back, in blocks of
    points."""
    n_lev, n_pts, nf = lnf.shape
    n_blocks = (n_pts + _BLOCK - 1) // _BLOCK
    for b in nb.prange(n_blocks):
        for n in range(b * _BLOCK, min(n_pts, (b + 1) * _BLOCK)):
            for lev in range(n_lev):
                for f in range(nf):
                    if to_flat:
                        flat[n, lev * nf + f] = lnf[lev, n, f]
                    else:
                        lnf[lev, n, f] = flat[n, lev * nf + f]


def _levels(res: np.ndarray, threads: int = 0) -> np.ndarray:
    """Level order of the level-parallel loops: numba hands thread ``t`` of ``T`` the ``t``-th
    contiguous part of the loop, so the order deals levels out round-robin (thread ``t`` gets
    levels ``t, t + T, …``): every thread gets coarse (cheap, cached) and fine (hashed,
    cache-missing) levels alike and they finish together (a contiguous split gave one thread
    all the fine levels). ``threads``: 0 = numba's current thread count."""
    t = max(1, min(threads or nb.get_num_threads(), len(res)))
    return np.concatenate([np.arange(k, len(res), t) for k in range(t)]).astype(np.int64)


def hashgrid_forward(x: np.ndarray, table: np.ndarray, res: np.ndarray, offsets: np.ndarray,
                     hashed: np.ndarray, out: np.ndarray) -> None:
    """Encode points.

    Args:
        x: float32 ``[N, 3]`` points in the unit cube (clamped to it by the caller).
        table: float32 ``[T, F]`` feature table, levels concatenated.
        res: int64 ``[L]`` grid resolution (cells per axis) of each level.
        offsets: int64 ``[L + 1]`` first table row of each level (``offsets[L] == T``).
        hashed: bool ``[L]`` whether the level is hashed.
        out: float32 ``[N, L * F]`` written in place.

    Each level is encoded into its own contiguous ``[N, F]`` slice of a scratch array, which is
    then interleaved into ``out``: a level loop writing ``out``'s columns directly touches
    every ``L * F * 4``-byte row of ``out`` once per level. With the round-robin levels and the
    branch-free cell, forward and backward take ~0.75x the time of the column-writing kernels
    on 131 k samples of lego training rays.
    """
    n_lev, nf = len(res), table.shape[1]
    scratch = np.empty((n_lev, x.shape[0], nf), dtype=np.float32)
    _forward_levels(x, table, res, offsets, hashed, _levels(res), scratch)
    _swap_axes(scratch, out, True)


def hashgrid_backward(x: np.ndarray, grad_out: np.ndarray, res: np.ndarray,
                      offsets: np.ndarray, hashed: np.ndarray, grad_table: np.ndarray) -> None:
    """Add ``d loss / d table`` into ``grad_table`` (float32 ``[T, F]``; zero it first for the
    gradient alone).

    ``grad_out`` is the output gradient, float32 ``[N, L * F]`` (C-contiguous). Each level owns
    a disjoint slice of the table, so threads never write the same row and the result does not
    depend on the thread count.
    """
    n_lev, nf = len(res), grad_table.shape[1]
    grad_lnf = np.empty((n_lev, x.shape[0], nf), dtype=np.float32)
    _swap_axes(grad_lnf, grad_out, False)
    _backward_levels(x, grad_lnf, res, offsets, hashed, _levels(res), grad_table)
