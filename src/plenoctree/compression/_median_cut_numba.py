"""numba kernel of :func:`plenoctree.compression.quantize.median_cut` (imported on first use).

Each set is copied once into a work array of rows ``(x, y, z)`` plus their original row ids;
at each level every bucket is a contiguous range of it, split in place by quickselect on the
key ``(value along the widest axis, row id)``. Rows move with their keys, so every pass reads
memory sequentially. Cost ``O(bits · N)`` per set; the sets (one per SH basis) run in parallel.
"""

from __future__ import annotations

import numba as nb
import numpy as np

__all__ = ["median_cut_batch"]

_SMALL = 16


@nb.njit(cache=True, inline="always")
def _swap(x, ids, a, b):
    for c in range(3):
        t = x[a, c]
        x[a, c] = x[b, c]
        x[b, c] = t
    t2 = ids[a]
    ids[a] = ids[b]
    ids[b] = t2


@nb.njit(cache=True, inline="always")
def _lt(va, ia, vb, ib):
    return va < vb or (va == vb and ia < ib)


@nb.njit(cache=True)
def _insertion_sort(x, ids, axis, lo, hi):
    for i in range(lo + 1, hi + 1):
        j = i
        while j > lo and _lt(x[j, axis], ids[j], x[j - 1, axis], ids[j - 1]):
            _swap(x, ids, j, j - 1)
            j -= 1


@nb.njit(cache=True)
def _select(x, ids, axis, lo, hi, k):
    """Reorder rows ``[lo, hi)`` so that the ``k`` smallest keys come first (0 < k < hi - lo)."""
    target = lo + k
    left = lo
    right = hi - 1
    while right > left:
        if right - left < _SMALL:
            _insertion_sort(x, ids, axis, left, right)
            return
        mid = (left + right) >> 1
        # median of three -> row mid
        if _lt(x[mid, axis], ids[mid], x[left, axis], ids[left]):
            _swap(x, ids, mid, left)
        if _lt(x[right, axis], ids[right], x[left, axis], ids[left]):
            _swap(x, ids, right, left)
        if _lt(x[right, axis], ids[right], x[mid, axis], ids[mid]):
            _swap(x, ids, right, mid)
        pv = x[mid, axis]
        pi = ids[mid]
        i = left
        j = right
        while i <= j:
            while _lt(x[i, axis], ids[i], pv, pi):
                i += 1
            while _lt(pv, pi, x[j, axis], ids[j]):
                j -= 1
            if i <= j:
                _swap(x, ids, i, j)
                i += 1
                j -= 1
        # [left, j] <= pivot <= [i, right]; a row strictly between holds the pivot itself.
        if target <= j:
            right = j
        elif target >= i:
            left = i
        else:
            return


@nb.njit(cache=True)
def _split(x, ids, lo, hi):
    """Split rows ``[lo, hi)`` in place; returns the size of the lower child.

    Zero range on every axis: no split (all rows stay in the lower child). Otherwise the
    quickselect median ``v`` along the widest axis, moved to the nearer boundary of its run
    of equal values, so equal values never straddle the cut.
    """
    m = hi - lo
    mn0 = x[lo, 0]
    mn1 = x[lo, 1]
    mn2 = x[lo, 2]
    mx0 = mn0
    mx1 = mn1
    mx2 = mn2
    for p in range(lo + 1, hi):
        v0 = x[p, 0]
        v1 = x[p, 1]
        v2 = x[p, 2]
        mn0 = min(mn0, v0)
        mx0 = max(mx0, v0)
        mn1 = min(mn1, v1)
        mx1 = max(mx1, v1)
        mn2 = min(mn2, v2)
        mx2 = max(mx2, v2)
    r0 = mx0 - mn0
    r1 = mx1 - mn1
    r2 = mx2 - mn2
    axis = 0
    best = r0
    if r1 > best:
        axis = 1
        best = r1
    if r2 > best:
        axis = 2
        best = r2
    if not best > 0:
        return m
    half = m // 2
    _select(x, ids, axis, lo, hi, half)
    v = x[lo + half, axis]
    n_less = 0
    n_leq = 0
    for p in range(lo, hi):
        val = x[p, axis]
        if val < v:
            n_less += 1
        if val <= v:
            n_leq += 1
    d_lo = half - n_less if n_less > 0 else m + 1
    d_hi = n_leq - half if n_leq < m else m + 1
    if d_lo < d_hi:
        # rows with value < v all lie in [lo, lo + half): move them to its front
        w = lo
        for p in range(lo, lo + half):
            if x[p, axis] < v:
                _swap(x, ids, p, w)
                w += 1
        return n_less
    # rows with value == v in [lo + half, hi): move them to its front
    w = lo + half
    for p in range(lo + half, hi):
        if x[p, axis] <= v:
            _swap(x, ids, p, w)
            w += 1
    return n_leq


@nb.njit(cache=True)
def _median_cut_one(pts, bits, codebook, index):
    n = pts.shape[0]
    x = pts.copy()
    ids = np.arange(n).astype(np.int64)
    n_max = 1 << bits
    starts = np.zeros(n_max + 1, dtype=np.int64)
    nxt = np.zeros(n_max + 1, dtype=np.int64)
    starts[1] = n
    n_buckets = 1
    for _level in range(bits):
        for b in range(n_buckets):
            lo = starts[b]
            hi = starts[b + 1]
            nxt[2 * b] = lo
            nxt[2 * b + 1] = lo + (_split(x, ids, lo, hi) if hi - lo >= 2 else hi - lo)
        n_buckets *= 2
        nxt[n_buckets] = n
        starts, nxt = nxt, starts
    for b in range(n_buckets):
        lo = starts[b]
        hi = starts[b + 1]
        if hi > lo:
            s0 = 0.0
            s1 = 0.0
            s2 = 0.0
            for p in range(lo, hi):
                s0 += x[p, 0]
                s1 += x[p, 1]
                s2 += x[p, 2]
                index[ids[p]] = b
            cnt = float(hi - lo)
            codebook[b, 0] = s0 / cnt
            codebook[b, 1] = s1 / cnt
            codebook[b, 2] = s2 / cnt


@nb.njit(cache=True, parallel=True)
def median_cut_batch(pts, bits, codebooks, index):
    """Median cut of ``pts [K, N, 3]`` float32 into ``codebooks [K, 2**bits, 3]`` float64 and
    ``index [K, N]`` uint16 (both preallocated, codebooks zeroed)."""
    for k in nb.prange(pts.shape[0]):
        _median_cut_one(pts[k], bits, codebooks[k], index[k])
