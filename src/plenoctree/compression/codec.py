"""The PlenOctree codec of paper B.2: per-basis median-cut codebooks, float16 σ, DEFLATE.

:func:`compress` turns an :class:`~plenoctree.octree.Octree` into a :class:`CompressedTree`
(in memory; :mod:`plenoctree.compression.fileio` writes it as a ``.plnz`` zip) and
:func:`decompress` turns it back into a normal tree. The input is never modified.

What is kept, per cell ``(node, i, j, k)`` (svox-compatible arrays):

- ``sigma`` float16 ``[n_nodes, 2, 2, 2]``: σ of every *kept* leaf (a leaf with
  ``σ > sigma_thresh``; values above float16's 65504 are clipped to it, which renders the
  same: such a leaf is opaque), 0 for every other cell (internal cells, empty or dropped
  leaves);
- ``quant_colors`` float16 ``[B - retain, 2**bits, 3]``: for each basis ``b >= retain`` a
  codebook of RGB triplets ``(k_R,b, k_G,b, k_B,b)`` fitted by median cut to the triplets of
  the kept leaves;
- ``quant_map`` uint16 ``[B - retain, n_nodes, 2, 2, 2]``: each kept leaf's codebook entry
  (0 for the other cells);
- ``data_retained`` float16 ``[retain, n_nodes, 2, 2, 2, 3]``: the first ``retain`` bases
  unquantised (0 outside kept leaves).

Decoding rule: a cell with ``σ > 0`` gets ``k_c,b = codebook_b[map_b][c]`` (or the retained
value); a cell with ``σ = 0`` gets all-zero data (its colour is never seen). So decompression
is exact for σ up to float16 rounding, and the colours differ only by the quantisation error.

Example::

    >>> from plenoctree.octree import Octree
    >>> t = Octree.dense(2, "SH4", seed=0)
    >>> ct = compress(t, CompressOptions(bits=8))
    >>> decompress(ct).data.shape == t.data.shape
    True
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._bounds import check_bounds
from ..errors import ConfigError, TreeFormatError
from ..octree import Octree
from .quantize import MAX_BITS, median_cut_many

__all__ = ["CompressOptions", "CompressedTree", "compress", "decompress"]

_FP16_MAX = float(np.finfo(np.float16).max)


@dataclass
class CompressOptions:
    """Settings of :func:`compress` (the ``compress`` / ``lod`` flags: the field docstrings
    are their help)."""

    bits: int = 16
    """codebook size 2^bits per SH basis function, 1..16 (the paper's 16)"""
    retain: int = 0
    """keep the first N basis functions unquantised, float16, 0..B (1 = the view-independent
    DC colour exact)"""
    sigma_thresh: float = 0.0
    """drop leaves with sigma <= this (1/world units): sigma set to 0 and left out of the
    codebook fit (svox's --sigma_thresh; 0 keeps every leaf with sigma > 0)"""
    level: int = 6
    """DEFLATE level 0..9 used when the file is written"""

    def validated(self, basis_dim: int | None = None) -> CompressOptions:
        """Return ``self`` after checking every field; raises :class:`ConfigError`."""
        for name, lo, hi in (("bits", 1, MAX_BITS), ("retain", 0, 10 ** 6), ("level", 0, 9)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not lo <= v <= hi:
                raise ConfigError(f"CompressOptions.{name} must be an integer in {lo}..{hi}, "
                                  f"got {v!r}")
        if basis_dim is not None and self.retain > basis_dim:
            raise ConfigError(f"CompressOptions.retain={self.retain} exceeds the tree's "
                              f"{basis_dim} basis functions")
        try:
            thr = float(self.sigma_thresh)
        except (TypeError, ValueError):
            raise ConfigError(f"CompressOptions.sigma_thresh must be a number, "
                              f"got {self.sigma_thresh!r}") from None
        if not math.isfinite(thr) or thr < 0:
            raise ConfigError(f"CompressOptions.sigma_thresh must be finite and >= 0, got {thr}")
        return check_bounds(self, "CompressOptions.")


@dataclass(eq=False)
class CompressedTree:
    """A compressed tree in memory (the arrays of a ``.plnz`` file).

    Attributes:
        child: int32 ``[n, 2, 2, 2]`` (as in :class:`Octree`).
        offset, invradius: float64 ``[3]``.
        data_format: ``"SH<B>" | "SG<B>" | "RGBA"``.
        extra_data: SG lobes float32 ``[B, 4]`` or None.
        depth_limit: as in :class:`Octree`.
        sigma: float16 ``[n, 2, 2, 2]``.
        quant_colors: float16 ``[B - retain, 2**bits, 3]``.
        quant_map: uint16 ``[B - retain, n, 2, 2, 2]``.
        data_retained: float16 ``[retain, n, 2, 2, 2, 3]``.
        options: the :class:`CompressOptions` used (``bits`` = log2 of the codebook size).
        ndc: the tree's :class:`~plenoctree.octree.ndc.NDCSpace` (forward-facing) or None.
    """

    child: np.ndarray
    offset: np.ndarray
    invradius: np.ndarray
    data_format: str
    extra_data: np.ndarray | None
    depth_limit: int
    sigma: np.ndarray
    quant_colors: np.ndarray
    quant_map: np.ndarray
    data_retained: np.ndarray
    options: CompressOptions = field(default_factory=CompressOptions)
    ndc: Any = None

    @property
    def n_nodes(self) -> int:
        return int(self.child.shape[0])

    @property
    def basis_dim(self) -> int:
        return int(self.quant_colors.shape[0] + self.data_retained.shape[0])

    @property
    def n_kept(self) -> int:
        """Leaves that carry data (σ > 0)."""
        return int(np.count_nonzero(self.sigma > 0))

    @property
    def nbytes(self) -> int:
        """Bytes of the arrays before DEFLATE."""
        arrays = (self.child, self.sigma, self.quant_colors, self.quant_map, self.data_retained)
        return int(sum(a.nbytes for a in arrays))

    def validate(self, name: str = "compressed tree") -> None:
        """Raise :class:`TreeFormatError` (``"<name>: <problem>"``) on inconsistent arrays.

        Checks shapes and dtypes against each other, the topology of ``child`` and its depth
        (:func:`plenoctree.octree.check.check_child`: depth <= ``depth_limit`` <= ``MAX_DEPTH``;
        ``depth_limit = -1`` means unset), finite values, and that every codebook index used by
        a cell with σ > 0 lies inside its codebook.
        """
        def fail(problem: str) -> None:
            raise TreeFormatError(f"{name}: {problem}")

        n = self.child.shape[0] if self.child.ndim == 4 else -1
        if self.child.ndim != 4 or self.child.shape[1:] != (2, 2, 2) or n < 1:
            fail(f"'child' must have shape [n_nodes, 2, 2, 2], got {list(self.child.shape)}")
        if self.child.dtype.kind not in "iu":
            fail(f"'child' must be an integer array, got {self.child.dtype}")
        from ..octree.check import check_box, check_child
        from ..octree.limits import MAX_DEPTH

        check_child(self.child, MAX_DEPTH if self.depth_limit == -1 else self.depth_limit, name)
        for key in ("offset", "invradius"):
            v = np.asarray(getattr(self, key))
            if v.shape != (3,) or v.dtype.kind != "f" or not np.isfinite(v).all():
                fail(f"{key!r} must be 3 finite floats, got {v.dtype} {v.tolist()}")
        check_box(self.offset, self.invradius, name)
        cells = (n, 2, 2, 2)
        if self.sigma.shape != cells:
            fail(f"'sigma' must have shape {list(cells)}, got {list(self.sigma.shape)}")
        qc, qm, dr = self.quant_colors, self.quant_map, self.data_retained
        if qc.ndim != 3 or qc.shape[2] != 3:
            fail(f"'quant_colors' must have shape [bases, codebook size, 3], got {list(qc.shape)}")
        if qm.shape != (qc.shape[0],) + cells:
            fail(f"'quant_map' must have shape {[qc.shape[0], *cells]}, got {list(qm.shape)}")
        if dr.ndim != 6 or dr.shape[1:] != cells + (3,):
            fail(f"'data_retained' must have shape [retain, {n}, 2, 2, 2, 3], "
                 f"got {list(dr.shape)}")
        if qm.dtype.kind not in "iu":
            fail(f"'quant_map' must be an integer array, got {qm.dtype}")
        from ..octree.tree import parse_data_format

        try:
            kind, b = parse_data_format(self.data_format)
        except TreeFormatError as e:
            fail(str(e))
        if qc.shape[0] + dr.shape[0] != b:
            fail(f"{self.data_format} has {b} basis functions but the file holds "
                 f"{qc.shape[0]} quantised + {dr.shape[0]} retained")
        if qc.shape[0] and qc.shape[1] < 1:
            fail("'quant_colors' has an empty codebook")
        for key, arr in (("sigma", self.sigma), ("quant_colors", qc), ("data_retained", dr)):
            if arr.dtype.kind != "f":
                fail(f"{key!r} must be a float array, got {arr.dtype}")
            if not np.isfinite(arr).all():
                fail(f"{key!r} holds NaN or infinite values")
        if (self.sigma < 0).any():
            fail("'sigma' holds negative values")
        on = self.sigma > 0
        for q in range(qm.shape[0]):
            used = qm[q][on]
            if used.size and (int(used.max()) >= qc.shape[1] or int(used.min()) < 0):
                bad = int(used.max()) if int(used.max()) >= qc.shape[1] else int(used.min())
                fail(f"codebook index {bad} out of range for basis {dr.shape[0] + q} "
                     f"(codebook has {qc.shape[1]} entries)")
        if kind == "SG":
            ed = self.extra_data
            if ed is None or ed.shape != (b, 4):
                fail(f"{self.data_format} needs 'extra_data' of shape [{b}, 4]")


def _leaf_coefficients(tree: Octree, keep: np.ndarray) -> np.ndarray:
    """Colour coefficients of the kept cells as RGB triplets per basis: float32 ``[B, M, 3]``."""
    b = tree.basis_dim
    rows = tree.data[keep]                                 # [M, D]
    if tree.data_format == "RGBA":
        coef = rows[:, :3].reshape(-1, 3, 1)
    else:
        coef = rows[:, :-1].reshape(-1, 3, b)              # channel-major -> [M, 3, B]
    return np.ascontiguousarray(np.transpose(coef, (2, 0, 1)), dtype=np.float32)


def compress(tree: Octree, options: CompressOptions | None = None) -> CompressedTree:
    """Quantise a tree's colours by per-basis median cut (paper B.2); ``tree`` is not modified.

    Args:
        tree: a valid tree (any data format; float16 or float32 data).
        options: :class:`CompressOptions` (defaults: 16 bits, no retained bases, keep every
            leaf with σ > 0).

    Returns:
        A :class:`CompressedTree`; write it with
        :func:`~plenoctree.compression.fileio.save_compressed`.

    Raises:
        ConfigError: bad options. TreeFormatError: the tree fails ``check_integrity`` or
        holds non-finite values.
    """
    opts = (options or CompressOptions()).validated(tree.basis_dim)
    tree.check_integrity("compress: tree")
    data = tree.data
    if not np.isfinite(data).all():
        raise TreeFormatError("compress: tree data holds NaN or infinite values")
    n = tree.n_nodes
    sigma = np.minimum(np.maximum(data[..., -1].astype(np.float32), 0.0), _FP16_MAX)
    keep = (tree.child == 0) & (sigma > float(opts.sigma_thresh))
    sigma16 = np.where(keep, sigma, 0.0).astype(np.float16)
    keep &= sigma16 > 0                                    # σ below float16's range -> empty
    sigma16[~keep] = 0
    coef = _leaf_coefficients(tree, keep)                  # [B, M, 3]
    r = int(opts.retain)
    retained = np.zeros((r, n, 2, 2, 2, 3), dtype=np.float16)
    if r:
        retained[:, keep] = np.clip(coef[:r], -_FP16_MAX, _FP16_MAX).astype(np.float16)
    codebooks, index = median_cut_many(coef[r:], int(opts.bits))
    quant_map = np.zeros((coef.shape[0] - r, n, 2, 2, 2), dtype=np.uint16)
    quant_map[:, keep] = index
    quant_colors = np.clip(codebooks, -_FP16_MAX, _FP16_MAX).astype(np.float16)
    extra = None if tree.extra_data is None else tree.extra_data.astype(np.float32).copy()
    return CompressedTree(child=tree.child.copy(), offset=tree.offset.copy(),
                          invradius=tree.invradius.copy(), data_format=tree.data_format,
                          extra_data=extra, depth_limit=int(tree.depth_limit), sigma=sigma16,
                          quant_colors=quant_colors, quant_map=quant_map,
                          data_retained=retained, options=opts, ndc=tree.ndc)


def decompress(ctree: CompressedTree, name: str = "compressed tree") -> Octree:
    """Rebuild a normal :class:`Octree` (float32 data) from a :class:`CompressedTree`.

    Cells with σ > 0 get their codebook (or retained) coefficients; every other cell is all
    zeros. Raises :class:`TreeFormatError` naming ``name`` when the arrays are inconsistent or
    a codebook index is out of range.
    """
    ctree.validate(name)
    b = ctree.basis_dim
    r = ctree.data_retained.shape[0]
    rgba = ctree.data_format == "RGBA"
    d = 4 if rgba else 3 * b + 1
    n = ctree.n_nodes
    on = np.flatnonzero(ctree.sigma.reshape(-1) > 0)        # kept cells, flat index
    coef = np.empty((on.size, 3, b), dtype=np.float32)      # channel-major rows [M, 3, B]
    for basis in range(b):
        if basis < r:
            vals = ctree.data_retained[basis].reshape(-1, 3).take(on, axis=0)
        else:
            q = basis - r
            vals = ctree.quant_colors[q].take(ctree.quant_map[q].reshape(-1).take(on), axis=0)
        coef[:, :, basis] = vals
    data = np.zeros((n * 8, d), dtype=np.float32)
    rows = np.empty((on.size, d), dtype=np.float32)
    rows[:, :-1] = coef.reshape(on.size, 3) if rgba else coef.reshape(on.size, 3 * b)
    rows[:, -1] = ctree.sigma.reshape(-1).take(on)
    data[on] = rows
    data = data.reshape(n, 2, 2, 2, d)
    tree = Octree(child=ctree.child.copy(), data=data, offset=ctree.offset.copy(),
                  invradius=ctree.invradius.copy(), data_format=ctree.data_format,
                  extra_data=None if ctree.extra_data is None else ctree.extra_data.copy(),
                  depth_limit=int(ctree.depth_limit), ndc=ctree.ndc)
    tree.check_integrity(name)
    return tree
