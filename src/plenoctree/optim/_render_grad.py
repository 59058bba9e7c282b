"""Python side of the numba fine-tuning kernels: argument packing and per-thread gradient slabs.

Nothing here compiles at import; :mod:`._render_grad_numba` is imported on first use.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .._util import to_numpy
from ..errors import ConfigError
from ..render._spec import TreeSpec, tree_spec
from ..render.options import RenderOptions

_CHUNK_TILES = 2     # grad_kernel's prange chunk, in tiles of TILE rays (dynamic only under tbb)

__all__ = ["SparseGrad", "kernel_args", "default_chunks", "forward_numba",
           "backward_numba", "fused_mse_numba"]


def _kernels():
    from . import _render_grad_numba

    return _render_grad_numba


def default_chunks() -> int:
    """Gradient slabs = numba worker threads (one dense slab per thread)."""
    import numba

    return max(1, int(numba.get_num_threads()))


def kernel_args(tree: Any, options: RenderOptions | None = None,
                skip_from: np.ndarray | None = None) -> TreeSpec:
    """Pack ``tree`` (an :class:`~plenoctree.octree.Octree`, geometry only) and ``options`` into
    the renderer's :class:`~plenoctree.render._spec.TreeSpec` (values passed to each launch).

    ``skip_from``: values ``[n_cells, D]`` whose empty leaves (σ ≤ 0) the kernels may skip
    (:mod:`plenoctree.render.empty_skip`). Only for values that never turn an empty leaf
    non-empty — fine-tuning from them: a σ ≤ 0 leaf gets no gradient and stays empty — not
    for arbitrary values (gradcheck, autograd)."""
    from ..render.empty_skip import skip_tables

    skip = None
    if skip_from is not None:
        flat = np.ascontiguousarray(to_numpy(tree.child), dtype=np.int32).reshape(-1)
        skip = skip_tables(flat, np.asarray(skip_from).reshape(flat.shape[0], -1))
    return tree_spec(tree, options, skip=skip)


class SparseGrad:
    """Per-thread compact gradient slabs (see :mod:`._render_grad_numba`).

    Slab ``t`` holds a row per cell its thread touched in the current batch, in touch order:
    ``grad3 [n_chunks, cap, D]``, ``touched`` int64 ``[n_chunks, cap]`` (row → cell),
    ``slot`` int32 ``[n_chunks, n_cells]`` (cell → row, ``-1`` untouched), ``n_touched`` /
    ``need`` int64 ``[n_chunks]`` (rows used / cells that found the slab full). ``cap`` starts
    at ``capacity`` (default ``min(n_cells, 2¹⁶)``) and grows with :meth:`grow` when a batch
    reaches more cells (the kernels' wrapper then runs the batch again), so the memory is set by
    the cells one batch reaches, not by the tree. After :meth:`merge` the dense gradient
    ``grad [n_cells, D]`` and :meth:`touched_cells` are valid (the autograd path).
    """

    def __init__(self, n_cells: int, dim: int, dtype: Any = np.float32,
                 n_chunks: int | None = None, capacity: int | None = None) -> None:
        self.n_chunks = int(n_chunks) if n_chunks else default_chunks()
        self.n_cells, self.dim, self.dtype = int(n_cells), int(dim), np.dtype(dtype)
        self.slot = np.full((self.n_chunks, self.n_cells), -1, dtype=np.int32)
        self.n_touched = np.zeros(self.n_chunks, dtype=np.int64)
        self.need = np.zeros(self.n_chunks, dtype=np.int64)
        self.sse = np.zeros(self.n_chunks, dtype=np.float64)
        self.regrown = 0                     # batches run again after a growth
        cap = min(self.n_cells, 1 << 16) if capacity is None else int(capacity)
        self._allocate(max(1, min(cap, self.n_cells)))
        self.grad: np.ndarray | None = None
        self._cells = np.zeros(0, dtype=np.int64)

    def _allocate(self, cap: int) -> None:
        self.cap = int(cap)
        self.grad3 = np.zeros((self.n_chunks, self.cap, self.dim), dtype=self.dtype)
        self.touched = np.zeros((self.n_chunks, self.cap), dtype=np.int64)

    @property
    def nbytes(self) -> int:
        """Bytes held by the slabs, lists and slot maps."""
        return int(self.grad3.nbytes + self.touched.nbytes + self.slot.nbytes)

    def grow(self) -> None:
        """After a batch that overflowed (``need.any()``): drop its partial gradient and make
        every slab large enough for all the cells that batch reached (at least twice as large),
        so running the batch again cannot overflow."""
        wanted = int((self.n_touched + self.need).sum())
        self.slot.fill(-1)
        self.n_touched[:] = 0
        self.need[:] = 0
        self._allocate(min(self.n_cells, max(2 * self.cap, wanted)))
        self.regrown += 1

    def merge(self) -> None:
        """Sum the slabs into the dense gradient :attr:`grad` ``[n_cells, D]`` (allocated
        here), note the touched cells, and clear the slabs."""
        cells = np.unique(np.concatenate([self.touched[c, : int(self.n_touched[c])]
                                          for c in range(self.n_chunks)]))
        dense = np.zeros((self.n_cells, self.dim), dtype=self.dtype)
        _kernels().merge_chunks(self.grad3, self.slot, self.touched, self.n_touched, dense)
        self.grad, self._cells = dense, cells

    def touched_cells(self) -> np.ndarray:
        """Cells with a gradient in the merged batch, sorted, int64 ``[M]``."""
        return self._cells


def _rays(origins: Any, dirs: Any) -> tuple[np.ndarray, np.ndarray]:
    o = np.ascontiguousarray(to_numpy(origins), dtype=np.float32).reshape(-1, 3)
    d = np.ascontiguousarray(to_numpy(dirs), dtype=np.float32).reshape(-1, 3)
    if o.shape != d.shape:
        raise ConfigError(f"origins and dirs must have the same shape, got {o.shape} and {d.shape}")
    return o, d


def _call(spec: TreeSpec, data2: np.ndarray, rays: tuple, rgb: np.ndarray,
          sg_buf: SparseGrad | None) -> None:
    """Run :func:`._render_grad_numba.grad_kernel` with values ``data2`` on ``rays = (origins,
    dirs, aux, mode, scale)`` (see the kernel), into ``rgb`` and the slabs of ``sg_buf`` (None:
    forward only), growing the slabs and running the batch again when they overflow."""
    k = _kernels()
    if sg_buf is None:  # forward only: zero-row slabs, one per thread
        nch = default_chunks()
        slabs = (np.zeros((nch, 0, data2.shape[1]), dtype=data2.dtype),
                 np.zeros((nch, 0), dtype=np.int32), np.zeros((nch, 0), dtype=np.int64),
                 np.zeros(nch, dtype=np.int64), np.zeros(nch, dtype=np.int64),
                 np.zeros(nch, dtype=np.float64))
    elif sg_buf.n_touched.any():        # a regrowth drops the slabs: they must hold nothing
        raise ConfigError("gradient slabs still hold a batch: merge or step before the next")
    import numba

    threads = numba.get_num_threads()
    old_chunk = numba.get_parallel_chunksize()
    numba.set_parallel_chunksize(_CHUNK_TILES)
    try:
        while True:
            if sg_buf is not None:
                slabs = (sg_buf.grad3, sg_buf.slot, sg_buf.touched, sg_buf.n_touched,
                         sg_buf.need, sg_buf.sse)
            grad3, need, sse = slabs[0], slabs[4], slabs[5]
            sse[:] = 0.0
            if threads > grad3.shape[0]:    # one slab per running thread (see grad_kernel)
                numba.set_num_threads(grad3.shape[0])
            spec.launch(k.grad_kernel, data2, rays, (spec.cap0, rgb) + slabs)
            if sg_buf is None or not need.any():
                break
            sg_buf.grow()                   # rare: larger slabs, the batch again
    finally:
        numba.set_num_threads(threads)
        numba.set_parallel_chunksize(old_chunk)


def forward_numba(args: TreeSpec, data2: np.ndarray, origins: Any, dirs: Any) -> np.ndarray:
    """Rendered rgb ``[N, 3]`` (dtype of ``data2 [n_cells, D]``), same values as the renderer."""
    o, d = _rays(origins, dirs)
    rgb = np.empty((o.shape[0], 3), dtype=np.float64)
    if o.shape[0]:
        _call(args, data2, (o, d, np.zeros((1, 3), np.float64), 2, 0.0), rgb, None)
    return rgb.astype(data2.dtype, copy=False)


def backward_numba(args: TreeSpec, data2: np.ndarray, origins: Any, dirs: Any,
                   grad_rgb: np.ndarray, buffers: SparseGrad | None = None) -> SparseGrad:
    """``∂L/∂data`` given ``∂L/∂rgb [N, 3]``; returns the merged :class:`SparseGrad`."""
    o, d = _rays(origins, dirs)
    g = np.ascontiguousarray(grad_rgb, dtype=np.float64).reshape(-1, 3)
    buf = buffers if buffers is not None else SparseGrad(data2.shape[0], data2.shape[1],
                                                         data2.dtype)
    if o.shape[0]:
        rgb = np.empty((o.shape[0], 3), dtype=np.float64)
        _call(args, data2, (o, d, g, 0, 0.0), rgb, buf)
    buf.merge()
    return buf


def fused_mse_numba(args: TreeSpec, data2: np.ndarray, origins: np.ndarray, dirs: np.ndarray,
                    targets: np.ndarray, scale: float, buffers: SparseGrad,
                    merge: bool = True) -> float:
    """One fused forward + backward of ``L = scale · Σ (C - target)²`` into ``buffers``
    (merged on return unless ``merge=False``: :func:`._render_grad_numba.step_touched` reads the
    slabs directly); returns the un-scaled sum of squared errors of the batch."""
    o, d = _rays(origins, dirs)
    t = np.ascontiguousarray(targets, dtype=np.float64).reshape(-1, 3)
    rgb = np.empty((o.shape[0], 3), dtype=np.float64)
    if o.shape[0]:
        _call(args, data2, (o, d, t, 1, float(scale)), rgb, buffers)
    if merge:
        buffers.merge()
    return float(buffers.sse.sum()) if o.shape[0] else 0.0
