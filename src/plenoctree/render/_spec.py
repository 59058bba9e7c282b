"""The prepared tree: one record of the arrays and options every numba march kernel takes.

The render kernel (:mod:`._render_numba`), the per-ray counters and the fine-tuning kernel
(:mod:`plenoctree.optim._render_grad_numba`) share one argument layout::

    kernel(child, skip, shift, data, offset, invr,      # TreeSpec.tree_args(data)
           <rays: origins, dirs and what the kernel makes of them>,
           kind, n_b, sg, b_lo, b_hi, bg, stop, eps,    # TreeSpec.shading_args()
           <the kernel's own tail: launch layout, outputs>)

:class:`TreeSpec` holds those fields once, built by :func:`tree_spec` from a tree and a
:class:`~.options.RenderOptions`, and :meth:`TreeSpec.launch` unpacks it into that call (numba
kernels take flat arrays and scalars, so the record stays on the Python side). Importing this
module compiles nothing and imports no numba.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from .._util import to_numpy, vec3
from .options import KIND_SG, FormatInfo, RenderOptions, parse_data_format

__all__ = ["TreeSpec", "tree_spec", "flat_tree", "initial_capacity"]


@dataclass(frozen=True)
class TreeSpec:
    """A tree's geometry and the renderer's options, packed as the numba kernels want them.

    ``data`` is the float32 ``[n_cells, D]`` values when the spec is made for rendering fixed
    values (:func:`plenoctree.render._render_numba.prepare`); the fine-tuner keeps ``None``
    and passes the values it trains to each launch.
    """

    child: np.ndarray          # int32 [n_cells] (with empty-skip rows: see .empty_skip)
    skip: np.ndarray           # uint8 [rows, 9] empty-space skips per ray octant, row grid
    shift: int                 # skip units -> integer coordinates
    offset: np.ndarray         # float64 [3]; tree coordinate = offset + invr * world
    invr: np.ndarray           # float64 [3]
    info: FormatInfo
    sg: np.ndarray             # float64 [B, 4] (SG) or [1, 4]
    b_lo: int                  # first and last basis used (RenderOptions.basis_range)
    b_hi: int
    bg: np.ndarray             # float64 [3] background
    stop: float                # early stop at T < stop
    eps: float                 # step_eps, tree units
    cap0: int                  # segments a fine-tuning ray record holds before it grows
    data: np.ndarray | None = None   # float32 [n_cells, D] values, or None (passed per launch)
    renorm: bool = False       # RenderOptions.renormalize (the render kernel's own argument)

    @property
    def n_cells(self) -> int:
        return int(self.child.shape[0])

    def tree_args(self, data: np.ndarray) -> tuple:
        """The kernels' leading arguments ``(child, skip, shift, data, offset, invr)``."""
        return (self.child, self.skip, self.shift, data, self.offset, self.invr)

    def shading_args(self) -> tuple:
        """The kernels' arguments after the rays: ``(kind, n_b, sg, b_lo, b_hi, bg, stop,
        eps)``."""
        return (self.info.kind, self.info.basis_dim, self.sg, self.b_lo, self.b_hi, self.bg,
                self.stop, self.eps)

    def launch(self, kernel: Callable[..., Any], data: np.ndarray | None, rays: tuple,
               tail: tuple) -> Any:
        """``kernel(*tree_args(data), *rays, *shading_args(), *tail)`` (``data`` None: the
        spec's own values)."""
        values = self.data if data is None else data
        return kernel(*self.tree_args(values), *rays, *self.shading_args(), *tail)


def flat_tree(child: Any, data: Any) -> tuple[np.ndarray, np.ndarray]:
    """The kernels' flat arrays: ``child`` int32 ``[n_cells]`` and ``data`` float32
    ``[n_cells, D]`` (no copy when they already are)."""
    child_flat = np.ascontiguousarray(to_numpy(child), dtype=np.int32).reshape(-1)
    d = to_numpy(data)
    return child_flat, np.ascontiguousarray(d, dtype=np.float32).reshape(child_flat.shape[0],
                                                                          d.shape[-1])


def tree_spec(tree: Any, options: RenderOptions | None = None, *,
              info: FormatInfo | None = None, skip: Any = None,
              with_values: bool = False) -> TreeSpec:
    """Pack ``tree`` (anything with ``child``, ``data``, ``offset``, ``invradius``,
    ``data_format`` and optionally ``extra_data``, ``depth_limit``: an
    :class:`~plenoctree.octree.Octree` or :class:`~plenoctree.render.CpuTree`) and ``options``.

    ``info``: the parsed format when the caller has it (else parsed and checked here);
    ``skip``: :class:`~.empty_skip.SkipTables` for the kernels to skip empty space with (None:
    every leaf is visited); ``with_values``: keep ``tree.data`` as float32 ``[n_cells, D]`` in
    the spec (the renderer) instead of ``None`` (the fine-tuner).
    """
    from .empty_skip import no_skip

    opts = (options if options is not None else RenderOptions()).validated()
    extra = getattr(tree, "extra_data", None)
    extra = None if extra is None else to_numpy(extra)
    if info is None:
        info = parse_data_format(tree.data_format, int(tree.data.shape[-1]), extra)
    if with_values:
        child, data = flat_tree(tree.child, tree.data)
    else:
        child, data = np.ascontiguousarray(to_numpy(tree.child), np.int32).reshape(-1), None
    tables = skip if skip is not None else no_skip(child)
    if extra is not None and info.kind == KIND_SG:
        sg = np.ascontiguousarray(extra, dtype=np.float64).reshape(info.basis_dim, 4)
    else:
        sg = np.zeros((1, 4), dtype=np.float64)
    b_lo, b_hi = opts.basis_range(info.basis_dim)
    return TreeSpec(tables.child, tables.skip, int(tables.shift), vec3(tree.offset),
                    vec3(tree.invradius), info, sg, b_lo, b_hi,
                    np.asarray(opts.background, dtype=np.float64), float(opts.stop_thresh),
                    float(opts.step_eps), initial_capacity(getattr(tree, "depth_limit", 10)),
                    data, bool(opts.renormalize))


def initial_capacity(depth_limit: int) -> int:
    """Segments a ray's record holds in the fine-tuning kernel before it grows: a ray crosses
    at most about ``3 · 2^(depth+1)`` finest cells of the box."""
    return int(3 * (2 << max(0, min(int(depth_limit), 20))) + 64)
