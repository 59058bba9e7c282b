"""Median-cut colour quantisation (Heckbert 1982), as used by the PlenOctree codec (paper B.2).

The set of RGB triplets is split ``bits`` times: at each level every bucket is cut at its
median along the RGB axis of largest range (``max - min``; ties pick the lowest axis). After
``bits`` levels there are ``2**bits`` buckets; a bucket's codebook entry is the mean of its
members (float64), an empty bucket's entry is 0.

The split is defined exactly, so that the fast kernel and its twin agree index for index:

- a bucket whose members are all equal (or that has fewer than 2) is not split: all of it goes
  to child ``2 b`` and child ``2 b + 1`` stays empty;
- otherwise let ``v`` be the median value along the split axis (element ``n // 2`` of the
  sorted values); child ``2 b`` gets the members with value ``< v`` or those with value
  ``<= v``, whichever cut lies nearer to ``n // 2`` without leaving a child empty (``< v`` on a
  tie). Equal values therefore never straddle a cut, and identical triplets always share a
  bucket (a plain count median would let a lone outlier share a bucket with many copies of
  another colour);
- bucket ids at the last level are the codebook indices.

``median_cut`` (numba, ``O(bits · N)`` via quickselect) and ``_median_cut_torch`` (the slow
twin, a sort per bucket) compute the same thing; the tests compare them.

Example::

    >>> import numpy as np
    >>> pts = np.random.default_rng(0).normal(size=(1000, 3)).astype(np.float32)
    >>> codebook, index = median_cut(pts, bits=4)
    >>> codebook.shape, index.shape, int(index.max()) < 16
    ((16, 3), (1000,), True)
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..errors import ConfigError

__all__ = ["median_cut", "median_cut_many", "MAX_BITS"]

#: Largest supported codebook size exponent (indices are stored as uint16).
MAX_BITS = 16


def _check_args(points: Any, bits: int, name: str = "points") -> np.ndarray:
    if isinstance(bits, bool) or not isinstance(bits, (int, np.integer)):
        raise ConfigError(f"median cut: bits must be an integer, got {bits!r}")
    if not 1 <= int(bits) <= MAX_BITS:
        raise ConfigError(f"median cut: bits must be in 1..{MAX_BITS}, got {bits}")
    pts = np.asarray(points)
    if pts.ndim < 2 or pts.shape[-1] != 3:
        raise ValueError(f"{name}: expected shape [..., N, 3], got {tuple(pts.shape)}")
    pts = np.ascontiguousarray(pts, dtype=np.float32)
    if not np.isfinite(pts).all():
        raise ValueError(f"{name}: contains NaN or infinite values")
    return pts


def median_cut(points: Any, bits: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Quantise RGB triplets by median cut into ``2**bits`` colours (numba kernel).

    Args:
        points: float ``[N, 3]`` (any units; converted to float32).
        bits: number of binary splits, ``1..16``; the codebook has ``2**bits`` entries.

    Returns:
        ``(codebook, index)``: float64 ``[2**bits, 3]`` bucket means (0 for empty buckets) and
        uint16 ``[N]`` bucket of each point, so ``codebook[index]`` approximates ``points``.
    """
    pts = _check_args(points, bits)
    if pts.ndim != 2:
        raise ValueError(f"points: expected shape [N, 3], got {tuple(pts.shape)}")
    codebook, index = median_cut_many(pts[None], bits)
    return codebook[0], index[0]


def median_cut_many(points: Any, bits: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Median cut of several independent sets at once (one per SH basis), in parallel.

    Args:
        points: float ``[K, N, 3]``: K sets of N triplets each.
        bits: ``1..16``.

    Returns:
        ``(codebooks float64 [K, 2**bits, 3], index uint16 [K, N])``.
    """
    pts = _check_args(points, bits)
    if pts.ndim != 3:
        raise ValueError(f"points: expected shape [K, N, 3], got {tuple(pts.shape)}")
    from ._median_cut_numba import median_cut_batch

    k, n = pts.shape[:2]
    codebooks = np.zeros((k, 1 << int(bits), 3), dtype=np.float64)
    index = np.zeros((k, n), dtype=np.uint16)
    if n:
        median_cut_batch(pts, int(bits), codebooks, index)
    return codebooks, index


def _median_cut_torch(points: Any, bits: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """The slow twin of :func:`median_cut` (torch, one stable sort per bucket and level).

    Same arguments and results; used by the tests as the specification.
    """
    import torch

    pts_np = _check_args(points, bits)
    if pts_np.ndim != 2:
        raise ValueError(f"points: expected shape [N, 3], got {tuple(pts_np.shape)}")
    pts = torch.from_numpy(pts_np)
    n = pts.shape[0]
    buckets: list[torch.Tensor] = [torch.arange(n, dtype=torch.int64)]
    for _ in range(int(bits)):
        nxt: list[torch.Tensor] = []
        for members in buckets:
            m = members.numel()
            if m < 2:
                nxt += [members, members[:0]]
                continue
            vals = pts[members]
            rng = vals.max(dim=0).values - vals.min(dim=0).values
            if not bool((rng > 0).any()):          # all equal: no split
                nxt += [members, members[:0]]
                continue
            axis = int(torch.argmax(rng))          # first maximum = lowest axis on ties
            key = pts[members, axis]
            v = torch.sort(key).values[m // 2]     # the median value
            n_less = int((key < v).sum())
            n_leq = int((key <= v).sum())
            d_lo = m // 2 - n_less if n_less > 0 else m + 1
            d_hi = n_leq - m // 2 if n_leq < m else m + 1
            low = key < v if d_lo < d_hi else key <= v
            nxt += [members[low], members[~low]]
        buckets = nxt
    codebook = np.zeros((1 << int(bits), 3), dtype=np.float64)
    index = np.zeros(n, dtype=np.uint16)
    for b, members in enumerate(buckets):
        if members.numel():
            codebook[b] = pts[members].double().mean(dim=0).numpy()
            index[members.numpy()] = b
    return codebook, index
