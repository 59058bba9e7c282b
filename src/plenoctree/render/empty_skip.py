"""Empty-space skipping for the numba renderer: how far a ray may jump from an empty leaf.

A leaf whose σ is ≤ 0 adds nothing to a ray (no weight, no colour, transmittance unchanged),
so a ray inside one may skip ahead over any region that holds only such leaves — the image is
the same (the torch twin, which visits every leaf, stays the spec) up to the lookups' ε push:
a leaf is looked up at ``p(t + ε)``, so where a ray crosses less than ``ε`` of a leaf, the
march jumps that sliver and gives it to the next leaf; a skip ends at other points than the
leaf-by-leaf march, so it meets other slivers (on lounge's far-field tree ≤ 5e-3 on ~1e-4 of
the pixels, where the march gave a sliver of empty space the next leaf's σ; flower within
2e-5, lego's 256³ tree bit for bit: ``benchmarks/render_speed.py``). Real trees are full of
small empty leaves around the surface (the octree can only be as coarse as its dyadic cells):
on lego's 256³ tree a ray that hits the box visits 17.7 leaves, 11.4 of them empty.

For each *ray octant* (the signs of the direction) and each empty leaf, :func:`skip_tables`
precomputes how far the leaf's exit planes may be pushed forward: on a grid of ``G³`` cells
(``G = 2^gbits``, at most 256, never finer than the tree) it marks the cells that any σ > 0
leaf overlaps, and a dynamic programme gives, per cell, the side ``k`` of the largest empty
cube that starts at the cell and grows in the octant's direction
(``k = 1 + min`` of the 7 forward neighbours). A leaf of side ``s`` cells whose back corner
(the corner a ray of that octant enters from) has ``k`` may exit at the far side of the cube:
``r = k - s`` more cells on every forward face. A ray of that octant inside the leaf only
moves forward, so everything it crosses before those planes lies inside the empty cube.

A tree whose detail sits in a small part of its root — a far field's tree is its box grown
``2^L`` times, with shells of coarser cells around it (:mod:`plenoctree.convert.shells`) —
gets nested grids about the root's centre, grid ``j`` over the cube ``2^j`` times smaller than
the root, down to cells as fine as the deepest leaves (at most :data:`MAX_NEST`); each empty
leaf skips on the finest grid that holds it whole, and a nested grid's cubes stop at its
border (what lies outside is another grid's). On lounge's grown tree (six shells, 2.88 M
leaves, 480×270 held-out views) a ray visits 60 leaves instead of 90 and a frame is ~1.3×
faster (`benchmarks/ab.py`, docs/results.md); one grid over the root skipped nothing there.

Result (:class:`SkipTables`): a copy of the flat ``child`` array in which every empty leaf
holds ``-(row + 1)`` instead of 0, and ``skip [rows, 9]`` uint8: columns 0–7 the ``r`` of each
octant in grid cells of the row's grid, column 8 how much finer that grid's cells are than
the root grid's (the kernel shifts ``r`` by ``shift - skip[row, 8]`` into its integer
coordinates); row 0 is all zeros,
the row of the empty leaves that cannot skip in any octant. So with the tables a leaf's
``child`` entry alone says whether it is empty: the kernels neither prefetch nor read the row
of an empty leaf (:func:`plenoctree.render._march_numba.look_ahead`). Leaves finer than a grid
cell use their grid cell (``r = k - 1``; 0 when the cell holds any σ > 0 leaf). On lego's
256³ tree (1.90 M leaves) the tables take 1–2 s to build and 12 MB (the ``child`` copy and
0.40 M rows), and a ray that hits the box visits 12.3 leaves
instead of 17.7 (a frame at 800²: 1.07× faster; the skipped segments are the cheap ones).

The tables describe the tree when they were made: a leaf that later gets σ > 0 by an in-place
edit would be skipped. Fine-tuning never does that (a leaf with σ ≤ 0 has no gradient and
stays empty); :func:`plenoctree.render.tree_to_device` builds the tables once for a tree that
renders many frames, and the renderer uses them only from there.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from .options import QUANT_BITS

__all__ = ["SkipTables", "skip_tables", "no_skip", "NO_SKIP", "MAX_GRID_BITS"]

#: Finest skip grid: 256³ cells (16 MiB per octant pass); finer gave no fewer segments on lego.
MAX_GRID_BITS = 8
#: Nested grids at most beyond the root's (each half the side of the one before, about the
#: root's centre): a far-field tree's box is ``2^L`` times smaller than its root (L <= 7), and a
#: refined box goes one or two levels deeper.
MAX_NEST = 9


@dataclass
class SkipTables:
    """What the kernel reads: ``child`` int32 ``[n_cells]`` (every empty leaf holds
    ``-(row + 1)``; row 0 skips nothing), ``skip`` uint8 ``[rows, 9]`` (grid cells per ray
    octant, octant ``4·[dx ≥ 0] + 2·[dy ≥ 0] + [dz ≥ 0]``; column 8: the row's grid, bits finer
    than the root grid), ``shift`` (root grid cells → the kernel's integer coordinates), and
    for reports ``grid_bits`` (of the root grid), ``seconds``."""

    child: np.ndarray
    skip: np.ndarray
    shift: int
    grid_bits: int = 0
    seconds: float = 0.0

    @property
    def nbytes(self) -> int:
        return int(self.child.nbytes + self.skip.nbytes)


#: The skip table of a plain ``child`` array (no entry refers to it).
NO_SKIP = np.zeros((1, 9), dtype=np.uint8)


def no_skip(child_flat: np.ndarray) -> SkipTables:
    """Tables that skip nothing (``child`` as it is): the kernels' path without skipping."""
    return SkipTables(child_flat, NO_SKIP, 0)


@njit(cache=True)
def _node_corners(child, n_nodes):
    """Depth and integer corner (``QUANT_BITS`` bits per axis) of every node; parents come
    before their children (offsets are positive)."""
    depth = np.zeros(n_nodes, np.int64)
    corner = np.zeros((n_nodes, 3), np.int64)
    max_level = 1
    for node in range(n_nodes):
        lv = depth[node] + 1                         # level of this node's cells
        max_level = max(max_level, lv)
        sh = QUANT_BITS - lv
        for c in range(8):
            off = child[node * 8 + c]
            if off > 0:
                ch = node + off
                depth[ch] = lv
                corner[ch, 0] = corner[node, 0] + (((c >> 2) & 1) << sh)
                corner[ch, 1] = corner[node, 1] + (((c >> 1) & 1) << sh)
                corner[ch, 2] = corner[node, 2] + ((c & 1) << sh)
    return depth, corner, max_level


@njit(cache=True)
def _leaf_box(depth, corner, cell):
    """Integer corner and side (``QUANT_BITS`` bits per axis) of flat cell ``cell``."""
    node = cell // 8
    c = cell % 8
    sh = QUANT_BITS - (depth[node] + 1)
    return (corner[node, 0] + (((c >> 2) & 1) << sh), corner[node, 1] + (((c >> 1) & 1) << sh),
            corner[node, 2] + ((c & 1) << sh), np.int64(1) << sh)


@njit(cache=True)
def _occupancy(child, data, depth, corner, lo, cbits, g, occ):
    """Mark the cells of the ``g³`` grid (corner ``lo``, cells of ``2^cbits`` integer units)
    that some σ > 0 leaf overlaps."""
    sig = data.shape[1] - 1
    hi = lo + (np.int64(g) << cbits)
    for cell in range(child.shape[0]):
        if child[cell] != 0 or not data[cell, sig] > 0.0:
            continue
        x, y, z, s = _leaf_box(depth, corner, cell)
        x0, y0, z0 = max(x, lo), max(y, lo), max(z, lo)
        x1, y1, z1 = min(x + s, hi), min(y + s, hi), min(z + s, hi)
        if x0 < x1 and y0 < y1 and z0 < z1:
            occ[(x0 - lo) >> cbits:((x1 - 1 - lo) >> cbits) + 1,
                (y0 - lo) >> cbits:((y1 - 1 - lo) >> cbits) + 1,
                (z0 - lo) >> cbits:((z1 - 1 - lo) >> cbits) + 1] = 1


@njit(cache=True)
def _empty_leaves(child, data, depth, corner, nest):
    """The empty leaves' cells and the finest nested grid (``0..nest``) holding each whole:
    grid ``j`` covers the cube of side ``2^(QUANT_BITS - j)`` about the root's centre."""
    sig = data.shape[1] - 1
    n_empty = 0
    for cell in range(child.shape[0]):
        if child[cell] == 0 and not data[cell, sig] > 0.0:
            n_empty += 1
    empty = np.empty(n_empty, np.int64)
    grid = np.zeros(n_empty, np.int64)
    mid = np.int64(1) << (QUANT_BITS - 1)
    j = 0
    for cell in range(child.shape[0]):
        if child[cell] == 0 and not data[cell, sig] > 0.0:
            x, y, z, s = _leaf_box(depth, corner, cell)
            m = max(mid - x, mid - y, mid - z, x + s - mid, y + s - mid, z + s - mid)
            half = mid
            k = 0
            while k < nest and (half >> 1) >= m:
                half >>= 1
                k += 1
            empty[j] = cell
            grid[j] = k
            j += 1
    return empty, grid


@njit(cache=True)
def _forward_cubes(occ, sx, sy, sz, out):
    """``out[x + 1, y + 1, z + 1]``: side (≤ 255) of the largest empty cube with its back corner
    at cell ``(x, y, z)``, growing towards ``+x`` if ``sx`` else ``-x`` (and so on). ``out`` is
    ``[g + 2]³`` with a border (255 where outside the grid is empty, 0 where it is unknown), so
    every cell reads its 7 forward neighbours without bounds checks."""
    g = occ.shape[0]
    ex = 1 if sx else -1
    ey = 1 if sy else -1
    ez = 1 if sz else -1
    for a in range(g):
        x = g - 1 - a if sx else a
        x1, nx = x + 1, x + 1 + ex
        for b in range(g):
            y = g - 1 - b if sy else b
            y1, ny = y + 1, y + 1 + ey
            for c in range(g):
                z = g - 1 - c if sz else c
                z1, nz = z + 1, z + 1 + ez
                if occ[x, y, z]:
                    out[x1, y1, z1] = 0
                    continue
                m = min(out[nx, y1, z1], out[x1, ny, z1], out[x1, y1, nz], out[nx, ny, z1],
                        out[nx, y1, nz], out[x1, ny, nz], out[nx, ny, nz])
                out[x1, y1, z1] = min(m + 1, 255)


@njit(cache=True)
def _octant_skips(empty, sel, depth, corner, lo, cbits, cubes, o, r):
    """``r[j, o]``: grid cells leaf ``empty[j]`` (``j`` in ``sel``) may extend its exit planes
    for octant ``o``, in the grid of corner ``lo`` and cells of ``2^cbits`` units."""
    sx, sy, sz = (o >> 2) & 1, (o >> 1) & 1, o & 1
    for j in sel:
        x, y, z, side = _leaf_box(depth, corner, empty[j])
        gx, gy, gz = (x - lo) >> cbits, (y - lo) >> cbits, (z - lo) >> cbits
        s = max(side >> cbits, 1)
        bx = gx if sx else gx + s - 1
        by = gy if sy else gy + s - 1
        bz = gz if sz else gz + s - 1
        r[j, o] = max(np.int64(cubes[bx + 1, by + 1, bz + 1]) - s, 0)


@njit(cache=True, parallel=True)
def _all_octants(occ, empty, sel, depth, corner, lo, cbits, border, r):
    """:func:`_forward_cubes` and :func:`_octant_skips` of the 8 octants, in parallel (each
    with its own ``[g + 2]³`` cubes, bordered by ``border``)."""
    g = occ.shape[0]
    for o in prange(8):
        cubes = np.full((g + 2, g + 2, g + 2), border, dtype=np.uint8)
        _forward_cubes(occ, (o >> 2) & 1, (o >> 1) & 1, o & 1, cubes)
        _octant_skips(empty, sel, depth, corner, lo, cbits, cubes, o, r)


def skip_tables(child_flat: np.ndarray, data2: np.ndarray) -> SkipTables:
    """:class:`SkipTables` of a tree: ``child_flat`` int32 ``[n_cells]`` (svox offsets),
    ``data2`` float ``[n_cells, D]`` (σ last). See the module docstring."""
    t0 = time.perf_counter()
    child_flat = np.ascontiguousarray(child_flat, dtype=np.int32)
    n_nodes = child_flat.shape[0] // 8
    depth, corner, max_level = _node_corners(child_flat, n_nodes)
    gbits = int(min(MAX_GRID_BITS, max_level))
    nest = int(min(max_level - gbits, MAX_NEST))
    empty, grid_of = _empty_leaves(child_flat, data2, depth, corner, nest)
    r = np.zeros((empty.size, 9), dtype=np.uint8)
    for j in range(nest + 1):
        sel = np.flatnonzero(grid_of == j)
        if sel.size == 0:
            continue
        # the root's grid and the finest one at 2^gbits cells a side, those between (a far
        # field's shells, whose cells are 2^(gbits-1) a side of their box) at half that
        bits = gbits if j in (0, nest) else gbits - 1
        cbits = QUANT_BITS - bits - j
        r[sel, 8] = QUANT_BITS - gbits - cbits
        lo = (1 << (QUANT_BITS - 1)) - (1 << (QUANT_BITS - 1 - j))
        occ = np.zeros((1 << bits,) * 3, dtype=np.uint8)
        _occupancy(child_flat, data2, depth, corner, lo, cbits, 1 << bits, occ)
        # Outside the root is empty; outside a nested grid is the coarser grids' business.
        _all_octants(occ, empty, sel, depth, corner, lo, cbits, 255 if j == 0 else 0, r)
    moves = r[:, :8].any(axis=1)
    rows = np.flatnonzero(moves)
    child = child_flat.copy()
    child[empty[~moves]] = -1                       # row 0: no skip in any octant
    child[empty[rows]] = -(np.arange(rows.size, dtype=np.int32) + 2)
    skip = np.concatenate([NO_SKIP, r[rows]])
    return SkipTables(child, skip, QUANT_BITS - gbits, gbits, time.perf_counter() - t0)
