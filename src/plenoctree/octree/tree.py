"""The PlenOctree data structure: svox-compatible arrays plus geometry helpers.

Tree space is the unit cube ``[0, 1]^3``; a world point ``x`` maps to ``offset + invradius * x``
(svox convention: ``invradius = 0.5 / radius``, ``offset = 0.5 - center * invradius``).
Node 0 (the root) spans the whole cube; cell ``(node, i, j, k)`` (``i`` along x, ``j`` along y,
``k`` along z) spans ``[c/2, (c+1)/2)`` of its node's cube per axis. A cell is a leaf when
``child[node, i, j, k] == 0``; otherwise its child node is ``node + child[node, i, j, k]``.
Cell depth = node depth; root cells have depth 0 and size 1/2 (tree units).

Example::

    >>> import numpy as np
    >>> t = Octree.dense(1, "RGBA")            # root + 8 children: 64 leaves of depth 1
    >>> t.n_nodes, t.n_leaves, t.leaf_sizes()[0].tolist()
    (9, 64, [0.5, 0.5, 0.5])
"""

from __future__ import annotations

import copy as _copy
import re
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import TreeFormatError
from .ndc import NDCSpace

__all__ = ["Octree", "parse_data_format"]

_SH_BASES = (1, 4, 9, 16, 25)
_MAX_DESCENT = 64      # float64 tree coordinates cannot resolve cells deeper than ~52 levels
_CELL_OFFSETS = np.stack(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij"), -1).reshape(8, 3)


def parse_data_format(data_format: Any) -> tuple[str, int]:
    """Split a data-format string into ``(kind, basis_dim)``; kind is ``"SH" | "SG" | "RGBA"``.

    ``"SH16" -> ("SH", 16)``, ``"SG25" -> ("SG", 25)``, ``"RGBA" -> ("RGBA", 1)``.
    Raises ``TreeFormatError`` for anything else (including svox's untested ``ASG#``).
    """
    if not isinstance(data_format, str):
        raise TreeFormatError(f"data_format must be a string, got {type(data_format).__name__}")
    if data_format == "RGBA":
        return "RGBA", 1
    m = re.fullmatch(r"(SH|SG)([0-9]{1,4})", data_format)
    if m is None:
        raise TreeFormatError(
            f"unknown data_format {data_format!r} (expected SH1/SH4/SH9/SH16/SH25, SG<B> or RGBA)")
    kind, n = m.group(1), int(m.group(2))
    if kind == "SH" and n not in _SH_BASES:
        raise TreeFormatError(f"data_format {data_format!r}: SH basis count must be one of "
                              f"{_SH_BASES}, got {n}")
    if kind == "SG" and n < 1:
        raise TreeFormatError(f"data_format {data_format!r}: SG needs at least one lobe")
    return kind, n


@dataclass(eq=False, repr=False)
class Octree:
    """A sparse octree of per-cell data, in the svox / volrend array layout.

    Attributes:
        child: int32 ``[n_nodes, 2, 2, 2]``; relative offset from a node to the child node of
            that cell (child node index = node + offset, always > node), 0 = the cell is a leaf.
        data: float32 ``[n_nodes, 2, 2, 2, data_dim]``; channel-major colour coefficients
            ``[R_0..R_{B-1}, G_0.., B_0..]`` (pre-sigmoid) then σ ≥ 0 (1/world-length) last.
            Data of internal (non-leaf) cells is stored but unused by the renderers.
        offset: float64 ``[3]``; tree coordinate = ``offset + invradius * world``.
        invradius: float64 ``[3]``; ``0.5 / radius`` per axis (1/world-length).
        data_format: ``"SH1" | "SH4" | "SH9" | "SH16" | "SH25" | "SG<B>" | "RGBA"``.
        extra_data: SG only: float32 ``[B, 4]`` (sharpness, mu_x, mu_y, mu_z); else None.
        depth_limit: maximum cell depth (root cells have depth 0; the leaves of a ``2^d`` grid
            have depth ``d - 1``). Passing -1 sets it to the tree's current maximum depth.
        ndc: forward-facing trees: the :class:`~plenoctree.octree.ndc.NDCSpace` their box lives
            in (world rays must be mapped to NDC before rendering); None for world-space trees.

    The constructor only converts types (``child`` to int32, ``offset``/``invradius`` to
    float64); call :meth:`check_integrity` to validate.
    """

    child: np.ndarray
    data: np.ndarray
    offset: np.ndarray
    invradius: np.ndarray
    data_format: str
    extra_data: np.ndarray | None = None
    depth_limit: int = -1
    ndc: NDCSpace | None = None

    def __post_init__(self) -> None:
        self.child = np.ascontiguousarray(self.child, dtype=np.int32)
        self.data = np.asarray(self.data)
        self.offset = np.asarray(self.offset, dtype=np.float64).reshape(-1)
        self.invradius = np.asarray(self.invradius, dtype=np.float64).reshape(-1)
        if self.offset.size == 1:
            self.offset = np.repeat(self.offset, 3)
        if self.invradius.size == 1:
            self.invradius = np.repeat(self.invradius, 3)
        if self.extra_data is not None:
            self.extra_data = np.asarray(self.extra_data, dtype=np.float32)
        self.depth_limit = int(self.depth_limit)
        if self.depth_limit < 0:
            try:
                self.depth_limit = max(self.max_depth, 0)
            except (TreeFormatError, ValueError, IndexError):
                self.depth_limit = 0    # malformed arrays: check_integrity() reports them

    # ------------------------------------------------------------------ sizes and format
    @property
    def n_nodes(self) -> int:
        """Number of nodes (each holds 2x2x2 cells)."""
        return int(self.child.shape[0])

    @property
    def n_leaves(self) -> int:
        """Number of leaf cells (``child == 0``)."""
        return int(np.count_nonzero(self.child == 0))

    @property
    def data_dim(self) -> int:
        """Values per cell: ``3 * basis_dim + 1``."""
        return int(self.data.shape[-1])

    @property
    def basis_dim(self) -> int:
        """Colour basis functions per channel: B of SH<B>/SG<B>; 1 for RGBA."""
        return parse_data_format(self.data_format)[1]

    @property
    def sh_degree(self) -> int | None:
        """SH degree (0..4) for SH formats, None otherwise."""
        kind, n = parse_data_format(self.data_format)
        return int(round(n ** 0.5)) - 1 if kind == "SH" else None

    @property
    def nbytes(self) -> int:
        """Bytes held by the arrays (child, data, offset, invradius, extra_data)."""
        extra = 0 if self.extra_data is None else self.extra_data.nbytes
        return int(self.child.nbytes + self.data.nbytes + self.offset.nbytes
                   + self.invradius.nbytes + extra)

    # ------------------------------------------------------------------ coordinates
    @property
    def radius(self) -> np.ndarray:
        """Half side of the tree's box per axis, world units, float64 ``[3]``."""
        return 0.5 / self.invradius

    @property
    def center(self) -> np.ndarray:
        """Centre of the tree's box, world units, float64 ``[3]``."""
        return (0.5 - self.offset) / self.invradius

    @property
    def bbox(self) -> np.ndarray:
        """World box ``[[min_x, min_y, min_z], [max_x, max_y, max_z]]``, float64 ``[2, 3]``."""
        return np.stack([self.center - self.radius, self.center + self.radius])

    def world_to_tree(self, x: Any) -> np.ndarray:
        """World points ``[..., 3]`` -> tree coordinates ``[..., 3]`` (box = [0, 1]^3), float64."""
        return self.offset + self.invradius * np.asarray(x, dtype=np.float64)

    def tree_to_world(self, x: Any) -> np.ndarray:
        """Tree coordinates ``[..., 3]`` -> world points ``[..., 3]``, float64."""
        return (np.asarray(x, dtype=np.float64) - self.offset) / self.invradius

    # ------------------------------------------------------------------ topology
    def _node_depths(self) -> np.ndarray:
        """Depth of every node (root 0), int64 ``[n_nodes]``; -1 for nodes not reachable.

        Assumes positive child offsets (see :meth:`check_integrity`).
        """
        return self._node_geometry()[0]

    def _node_geometry(self) -> tuple[np.ndarray, np.ndarray]:
        """``(depth [n_nodes] int64, corner [n_nodes, 3] float64)`` in tree units.

        A node of depth t spans ``corner + [0, 2^-t]^3``. Unreachable nodes get depth -1.
        Walks level by level from the root, vectorised per level.
        """
        n = self.n_nodes
        depth = np.full(n, -1, dtype=np.int64)
        corner = np.zeros((n, 3), dtype=np.float64)
        if n == 0:
            return depth, corner
        flat = self.child.reshape(n, 8)
        level = np.zeros(1, dtype=np.int64)
        depth[0] = 0
        t = 0
        while level.size:
            sub = flat[level]
            p, c = np.nonzero(sub > 0)
            if p.size == 0:
                break
            kids = level[p] + sub[p, c].astype(np.int64)
            if kids.max() >= n or (depth[kids] >= 0).any() or t >= n \
                    or np.unique(kids).size != kids.size:
                raise TreeFormatError("child offsets do not form a tree "
                                      "(out of range, shared child or cycle)")
            t += 1
            depth[kids] = t
            corner[kids] = corner[level[p]] + _CELL_OFFSETS[c] * (0.5 ** t)
            level = kids
        return depth, corner

    def node_depths(self) -> np.ndarray:
        """Depth of every node, int64 ``[n_nodes]`` (root 0; its cells have depth 0)."""
        return self._node_depths()

    @property
    def max_depth(self) -> int:
        """Largest cell depth present (0 for a root-only tree)."""
        if self.child.ndim != 4 or self.n_nodes == 0:
            return 0
        return int(self._node_depths().max())

    def leaf_indices(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(node, i, j, k)`` int64 arrays ``[n_leaves]`` of every leaf cell, in C order."""
        return tuple(a.astype(np.int64) for a in np.nonzero(self.child == 0))  # type: ignore

    def _leaf_geometry(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(depth [n], corner [n, 3], size [n])`` of every leaf cell, tree units."""
        node, i, j, k = self.leaf_indices()
        ndepth, ncorner = self._node_geometry()
        d = ndepth[node]
        size = 0.5 ** (d + 1)
        corner = ncorner[node] + np.stack([i, j, k], -1) * size[:, None]
        return d, corner, size

    def leaf_depths(self) -> np.ndarray:
        """Depth of every leaf cell, int64 ``[n_leaves]`` (order of :meth:`leaf_indices`)."""
        return self._leaf_geometry()[0]

    def leaf_centers(self) -> np.ndarray:
        """World-space centre of every leaf cell, float64 ``[n_leaves, 3]``."""
        _, corner, size = self._leaf_geometry()
        return self.tree_to_world(corner + 0.5 * size[:, None])

    def leaf_sizes(self) -> np.ndarray:
        """World-space side lengths of every leaf cell, float64 ``[n_leaves, 3]``."""
        _, _, size = self._leaf_geometry()
        return size[:, None] / self.invradius

    def leaf_data(self) -> np.ndarray:
        """Data of every leaf cell, ``[n_leaves, data_dim]`` (a copy; :meth:`leaf_indices` order)."""
        return self.data[self.child == 0]

    def set_leaf_data(self, values: Any) -> None:
        """Overwrite the data of every leaf cell with ``values [n_leaves, data_dim]`` (in place)."""
        values = np.asarray(values)
        want = (self.n_leaves, self.data_dim)
        if values.shape != want:
            raise ValueError(f"set_leaf_data: expected shape {want}, got {values.shape}")
        self.data[self.child == 0] = values.astype(self.data.dtype, copy=False)

    # ------------------------------------------------------------------ queries
    def query_cells(self, points: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                                np.ndarray]:
        """Leaf cell containing each world point.

        Args:
            points: world coordinates ``[..., 3]``.
        Returns:
            ``(node, i, j, k, inside)``, each ``[...]``; ``inside`` (bool) is False for points
            outside the tree's closed box (their indices are 0). Points on the far faces
            belong to the last cell.
        """
        p = np.asarray(points, dtype=np.float64)
        if p.shape[-1:] != (3,):
            raise ValueError(f"query: points must have shape [..., 3], got {list(p.shape)}")
        p = self.world_to_tree(p)
        shape = p.shape[:-1]
        p = p.reshape(-1, 3)
        inside = np.all((p >= 0.0) & (p <= 1.0), axis=-1)
        n = p.shape[0]
        node = np.zeros(n, dtype=np.int64)
        cell = np.zeros((n, 3), dtype=np.int64)
        act = np.nonzero(inside)[0]
        pos = p[act]
        cur = np.zeros(act.size, dtype=np.int64)
        flat = self.child.reshape(-1, 8)
        for _ in range(_MAX_DESCENT):
            if not act.size:
                break
            idx = np.minimum((pos * 2.0).astype(np.int64), 1)
            off = flat[cur, idx[:, 0] * 4 + idx[:, 1] * 2 + idx[:, 2]]
            done = off == 0
            node[act[done]] = cur[done]
            cell[act[done]] = idx[done]
            keep = ~done
            act, cur, pos, idx = act[keep], cur[keep] + off[keep], pos[keep], idx[keep]
            pos = pos * 2.0 - idx
        if act.size:
            raise TreeFormatError(f"query: descent deeper than {_MAX_DESCENT} levels "
                                  "(cyclic child offsets?)")
        return (node.reshape(shape), cell[:, 0].reshape(shape), cell[:, 1].reshape(shape),
                cell[:, 2].reshape(shape), inside.reshape(shape))

    def query(self, points: Any) -> np.ndarray:
        """Data of the leaf containing each world point; zeros outside the box.

        Args:
            points: world coordinates ``[..., 3]``.
        Returns:
            ``[..., data_dim]`` of ``data.dtype``.
        """
        node, i, j, k, inside = self.query_cells(points)
        out = self.data[node, i, j, k]
        out[~inside] = 0
        return out

    # ------------------------------------------------------------------ copies
    def copy(self) -> Octree:
        """A deep copy (all arrays copied)."""
        return _copy.deepcopy(self)

    def astype(self, dtype: Any) -> Octree:
        """A copy whose ``data`` has ``dtype`` (e.g. ``np.float16`` / ``np.float32``)."""
        out = self.copy()
        out.data = out.data.astype(dtype)
        return out

    def __repr__(self) -> str:
        c = ", ".join(f"{v:.4g}" for v in self.center)
        r = ", ".join(f"{v:.4g}" for v in self.radius)
        dim = self.data.shape[-1] if self.data.ndim else "?"
        return (f"Octree(data_format={self.data_format!r}, n_nodes={self.n_nodes}, "
                f"n_leaves={self.n_leaves}, data_dim={dim}, "
                f"dtype={self.data.dtype}, depth_limit={self.depth_limit}, "
                f"center=[{c}], radius=[{r}]" + (", ndc=True" if self.ndc is not None else "")
                + ")")

    # ------------------------------------------------------------------ builders / checks
    @classmethod
    def from_grid(cls, values: Any, mask: Any, center: Any = 0.0, radius: Any = 1.0,
                  data_format: str = "SH16", extra_data: Any = None) -> Octree:
        """Build a tree from a ``2^d`` grid; see :func:`plenoctree.octree.build.tree_from_grid`."""
        from .build import tree_from_grid
        return tree_from_grid(values, mask, center, radius, data_format, extra_data)

    @classmethod
    def dense(cls, depth: int, data_format: str = "SH1", center: Any = 0.0, radius: Any = 1.0,
              values: Any = None, seed: int | None = None, extra_data: Any = None) -> Octree:
        """A fully refined tree; see :func:`plenoctree.octree.build.dense_tree`."""
        from .build import dense_tree
        return dense_tree(depth, data_format, center, radius, values, seed, extra_data)

    def check_integrity(self, name: str = "tree") -> None:
        """Raise ``TreeFormatError`` (message ``"<name>: <problem>"``) unless the tree is valid.

        See :func:`plenoctree.octree.check.check_tree` for the list of checks.
        """
        from .check import check_tree
        check_tree(self, name)
