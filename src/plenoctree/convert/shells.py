"""The far field's shells around an extracted tree (issue 50; :mod:`plenoctree.nerf.far`).

The tree of an unbounded capture is the extracted tree's box grown ``2^L`` times about its
centre. Shell ``l`` (``1 <= l <= L``) is the box grown ``2^l`` times minus the box grown
``2^(l-1)`` times; it is cut into a ``far_grid^3`` grid over its outer cube (the inner half
left out), so its cells are ``2^l`` times as large as those of a ``far_grid^3`` grid over the
box: about the same angle seen from the centre, where the cameras stand. Each shell goes
through the steps of the box itself: σ at the cell centres, the max-weight visibility filter
over the training views, averaged samples of the kept cells. What a shell does not keep is
empty space, merged into leaves as coarse as the octree allows; the renderers draw the whole
tree as any other (the traversal is unchanged), and the box's leaves keep their values.

The filter of a shell sees neither the box nor the nearer shells (their cells count as
empty): it keeps every cell some view could see past them, a little more than needed. Kept
cells too thin to matter (opacity below ``min_alpha``) are left empty: every leaf a ray
crosses costs a step, and the far field's thin fog fills much of a shell.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import ConfigError
from .grid import GridSpec, evaluate_density_grid
from .sampling import SampleOptions, SamplingStats, sample_cells
from .visibility import visibility_weights, weight_mask

__all__ = ["ShellOptions", "shell_levels", "add_shells"]


@dataclass
class ShellOptions:
    """How :func:`add_shells` extracts the shells.

    Attributes:
        grid: cells per axis of each shell's grid (a power of two >= 4).
        weight_thresh: the visibility filter's τ_w. min_alpha: kept cells whose opacity
            ``1 - exp(-σ ℓ)`` is below this are left empty (the far field's fog: on lounge,
            0.01 drops 22 % of the leaves and 30 % of the leaves a ray visits at the same
            PSNR). samples: the :class:`SampleOptions` of
            the kept cells. backend, device: of the visibility filter
            (:func:`~.visibility.visibility_weights`; None: the CPU). show_progress: progress
            bars.
    """

    grid: int = 256
    weight_thresh: float = 0.001
    min_alpha: float = 0.01
    samples: SampleOptions = SampleOptions()
    backend: str = "auto"
    device: str | None = None
    show_progress: bool | None = None


def shell_levels(box_radius: np.ndarray, outer_radius: np.ndarray, depth: int) -> int:
    """Shells ``L`` for a box of ``box_radius [3]`` to reach the far field's outer cube of
    ``outer_radius [3]``, with the box's leaves at cell depth ``depth`` kept within
    ``MAX_DEPTH`` with 3 levels to spare for refinement."""
    from ..octree.limits import MAX_DEPTH

    ratio = float(np.max(np.asarray(outer_radius, np.float64) / np.asarray(box_radius,
                                                                             np.float64)))
    need = max(1, math.ceil(math.log2(max(ratio, 1.0)) - 1e-9))
    room = MAX_DEPTH - 3 - int(depth)
    if room < 1:
        raise ConfigError(f"no depth left for the far field's shells: the box's leaves are "
                          f"{depth} levels deep; use a smaller --grid")
    return min(need, room)


def _hole(n: int) -> np.ndarray:
    """bool ``[n, n, n]``: the cells of a shell's grid inside the next shell in (the half)."""
    a = np.arange(n)
    inner = (a >= n // 4) & (a < n - n // 4)
    return inner[:, None, None] & inner[None, :, None] & inner[None, None, :]


def _box_leaves(tree: Any, levels: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(depths, coords, values)`` of ``tree``'s non-empty leaves, in the grid of the tree
    grown ``2^levels`` times (a leaf of depth ``c`` goes ``levels`` deeper, shifted by
    ``(2^levels - 1) 2^c`` cells)."""
    node, x, y, z = tree.leaf_indices()
    vals = tree.data[node, x, y, z]
    keep = np.any(vals != 0, axis=1)
    depth = tree.leaf_depths()[keep].astype(np.int64)
    size = tree.leaf_sizes()[keep]                                    # [M, 3] world
    lo = tree.leaf_centers()[keep] - 0.5 * size
    ijk = np.rint((lo - (tree.center - tree.radius)) / size).astype(np.int64)
    shift = ((1 << levels) - 1) << depth
    return depth + levels, ijk + shift[:, None], vals[keep].astype(np.float32)


def _shell(field: Any, cams: Any, centre: np.ndarray, radius: np.ndarray, level: int,
           levels: int, opts: ShellOptions, limit: int | None, stats: SamplingStats
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(depths, coords, values)`` of shell ``level``'s kept cells in the grown tree's grid."""
    n = int(opts.grid)
    spec = GridSpec.make(centre, radius * float(2 ** level), n)
    sigma = evaluate_density_grid(field, spec, opts.samples.chunk, desc=f"shell {level} sigma",
                                  show_progress=opts.show_progress)
    hole = _hole(n)
    sigma[hole] = 0.0
    if not np.any(sigma > 0):
        return np.zeros(0, np.int64), np.zeros((0, 3), np.int64), None
    try:
        cand, weights = visibility_weights(sigma, spec, cams, opts.weight_thresh, opts.backend,
                                           opts.show_progress, limit, device=opts.device)
    except ConfigError:             # nothing dense enough to be seen: an empty shell
        return np.zeros(0, np.int64), np.zeros((0, 3), np.int64), None
    del sigma
    mask = weight_mask(spec, cand, weights, opts.weight_thresh) & ~hole
    flat = np.flatnonzero(mask)
    if flat.size == 0:
        return np.zeros(0, np.int64), np.zeros((0, 3), np.int64), None
    values = sample_cells(field, spec, flat, opts.samples, stats)
    alpha = 1.0 - np.exp(-np.maximum(values[:, -1], 0.0) * float(spec.cell.mean()))
    solid = alpha >= opts.min_alpha                     # fog a ray would cross unchanged
    flat, values = flat[solid], values[solid]
    ijk = np.stack(np.unravel_index(flat, (n,) * 3), -1).astype(np.int64)
    k = n.bit_length() - 1                                       # n = 2^k
    depth = levels - level - 1 + k
    corner = (1 << (k - 1)) * ((1 << (levels - level)) - 1)
    return np.full(flat.size, depth, np.int64), ijk + corner, values


def add_shells(tree: Any, field: Any, cams: Any, levels: int, opts: ShellOptions,
               limit: int | None = None) -> tuple[Any, dict]:
    """``tree`` (an extracted box) with ``levels`` shells of the far field around it.

    Args:
        tree: the extracted :class:`~plenoctree.octree.Octree` (its box is the inner box).
        field: the radiance field (a NeRF with a far field: ``NeRFField``).
        cams: the training :class:`~plenoctree.datasets.Cameras` (the visibility filter).
        levels: ``L >= 1`` (:func:`shell_levels`). opts: :class:`ShellOptions`.
        limit: memory budget in bytes of the visibility filter.

    Returns:
        ``(the grown tree, figures)``: figures hold ``far_levels`` and ``shell_leaves`` (kept
        cells per shell, innermost first).
    """
    from ..octree.build import tree_from_leaves

    n = int(opts.grid)
    if n < 4 or n & (n - 1):
        raise ConfigError(f"--far-grid must be a power of two >= 4, got {n}")
    centre, radius = np.asarray(tree.center, np.float64), np.asarray(tree.radius, np.float64)
    parts = [_box_leaves(tree, levels)]
    stats = SamplingStats()
    kept = []
    for level in range(1, levels + 1):
        d, c, v = _shell(field, cams, centre, radius, level, levels, opts, limit, stats)
        kept.append(int(d.size))
        if d.size:
            parts.append((d, c, v))
    depths, coords, values = (np.concatenate(x) for x in zip(*parts))
    grown = tree_from_leaves(depths, coords, values, centre, radius * float(2 ** levels),
                             tree.data_format, tree.extra_data)
    return grown, {"far_levels": int(levels), "far_grid": n, "shell_leaves": kept,
                   "inner_box": {"center": centre.tolist(), "radius": radius.tolist()}}
