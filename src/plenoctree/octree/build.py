"""Building octrees from voxel grids (vectorised numpy, level by level).

``tree_from_grid`` is the extraction step of the paper (§4.2): every occupied cell of a ``2^d``
grid becomes a leaf at the deepest level, empty space stays as coarse zero leaves. Nodes are
numbered breadth-first (a level's nodes ordered by parent, then by cell ``i, j, k``), so every
child offset is positive, as svox writes them.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..errors import TreeFormatError
from .check import expected_data_dim
from .tree import _CELL_OFFSETS, Octree, parse_data_format

__all__ = ["tree_from_grid", "tree_from_leaves", "dense_tree", "box_params"]

_CHUNK = 1 << 18            # parent nodes processed per block (bounds temporaries)


def box_params(center: Any, radius: Any) -> tuple[np.ndarray, np.ndarray]:
    """``(offset [3], invradius [3])`` float64 of the box ``center ± radius`` (scalars or [3])."""
    c = np.broadcast_to(np.asarray(center, dtype=np.float64), (3,)).copy()
    r = np.broadcast_to(np.asarray(radius, dtype=np.float64), (3,)).copy()
    if not (np.isfinite(c).all() and np.isfinite(r).all() and (r > 0).all()):
        raise ValueError(f"box: need finite center and radius > 0, got center={c.tolist()}, "
                         f"radius={r.tolist()}")
    inv = 0.5 / r
    return 0.5 - c * inv, inv


def _pyramid(mask: np.ndarray, d: int) -> list[np.ndarray]:
    """Occupancy per level: ``occ[t]`` bool ``[2^t]^3`` = any cell of ``mask`` inside, t = 0..d."""
    occ = [mask]
    for _ in range(d):
        m = occ[0]
        m = m[0::2] | m[1::2]
        m = m[:, 0::2] | m[:, 1::2]
        m = m[:, :, 0::2] | m[:, :, 1::2]
        occ.insert(0, m)
    return occ


def _check_format(data_format: str, data_dim: int, extra_data: Any) -> np.ndarray | None:
    try:
        kind, b = parse_data_format(data_format)
        want = expected_data_dim(data_format)
    except TreeFormatError as e:
        raise ValueError(str(e)) from None
    if data_dim != want:
        raise ValueError(f"values have {data_dim} channels but data_format {data_format!r} "
                         f"needs {want}")
    if kind == "SG":
        if extra_data is None or np.shape(extra_data) != (b, 4):
            raise ValueError(f"data_format {data_format!r} needs extra_data [{b}, 4] "
                             f"(sharpness, mu_x, mu_y, mu_z), got "
                             f"{None if extra_data is None else np.shape(extra_data)}")
        return np.asarray(extra_data, dtype=np.float32).copy()
    if extra_data is not None:
        raise ValueError(f"extra_data is only used by SG formats, not {data_format!r}")
    return None


def tree_from_grid(values: Any, mask: Any, center: Any = 0.0, radius: Any = 1.0,
                   data_format: str = "SH16", extra_data: Any = None) -> Octree:
    """Build the octree of a ``R = 2^d`` voxel grid (d >= 1) covering ``center ± radius``.

    Every cell with ``mask`` True becomes a leaf of depth ``d - 1`` (cell side ``2 radius / R``)
    holding its value; a node exists only where some cell below it is occupied, so empty space
    stays as large leaves with zero data. Internal cells hold zeros.

    Args:
        values: float ``[R, R, R, D]`` (grid index ``[x, y, z]``), or ``[M, D]`` with
            ``M = mask.sum()``: the values of the occupied cells in C order of
            ``np.nonzero(mask)`` (lets callers evaluate only occupied cells of a 512³ grid).
            Channel-major colour coefficients then σ >= 0 last; D must match ``data_format``.
        mask: bool ``[R, R, R]``, occupied cells.
        center, radius: world box (scalars or ``[3]``); tree space ``[0, 1]^3`` maps onto it.
        data_format: ``"SH<B>" | "SG<B>" | "RGBA"``.
        extra_data: SG lobes ``[B, 4]``; None otherwise.
    Returns:
        An :class:`Octree` with float32 data and ``depth_limit = d - 1``.
    Raises:
        ValueError: bad shapes, R not a power of two, non-finite values or σ < 0 in an
            occupied cell.

    Example::

        >>> m = np.zeros((4, 4, 4), bool); m[0, 0, 0] = True
        >>> t = tree_from_grid(np.ones((4, 4, 4, 4), np.float32), m, data_format="RGBA")
        >>> t.n_nodes, t.n_leaves, t.query(np.array([-0.9, -0.9, -0.9])).tolist()
        (2, 15, [1.0, 1.0, 1.0, 1.0])
    """
    mask = np.asarray(mask)
    if mask.dtype != np.bool_:
        raise ValueError(f"mask must be a bool array, got {mask.dtype}")
    if mask.ndim != 3 or len(set(mask.shape)) != 1:
        raise ValueError(f"mask must be a cube [R, R, R], got shape {list(mask.shape)}")
    res = mask.shape[0]
    d = int(res).bit_length() - 1
    if res < 2 or (1 << d) != res:
        raise ValueError(f"grid resolution must be a power of two >= 2, got {res}")
    values = np.asarray(values)
    dense = values.ndim == 4
    if dense:
        if values.shape[:3] != mask.shape:
            raise ValueError(f"values [R, R, R, D] must match mask {list(mask.shape)}, got "
                             f"{list(values.shape)}")
    elif values.ndim == 2:
        m = int(np.count_nonzero(mask))
        if values.shape[0] != m:
            raise ValueError(f"values [M, D] must have M = mask.sum() = {m} rows, got "
                             f"{values.shape[0]}")
    else:
        raise ValueError(f"values must be [R, R, R, D] or [M, D], got shape {list(values.shape)}")
    if values.dtype.kind not in "fiu":
        raise ValueError(f"values must be numeric, got {values.dtype}")
    dim = int(values.shape[-1])
    extra = _check_format(data_format, dim, extra_data)
    offset, invradius = box_params(center, radius)

    occ = _pyramid(mask, d)
    counts = [int(np.count_nonzero(o)) for o in occ[:d]]    # nodes per depth 0..d-1
    counts[0] = 1                                            # the root always exists
    starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    n_nodes = int(starts[-1])
    child = np.zeros((n_nodes, 8), dtype=np.int32)
    data = np.zeros((n_nodes, 8, dim), dtype=np.float32)
    sparse_keys = None if dense else np.flatnonzero(mask)

    coords = np.zeros((1, 3), dtype=np.int64)               # node cubes at depth t, res 2^t
    for t in range(d):
        level_res = 1 << (t + 1)
        nxt = occ[t + 1].reshape(-1)
        new_coords = []
        n_new = 0
        for a in range(0, len(coords), _CHUNK):
            cells = coords[a:a + _CHUNK, None, :] * 2 + _CELL_OFFSETS[None]      # [n, 8, 3]
            lin = (cells[..., 0] * level_res + cells[..., 1]) * level_res + cells[..., 2]
            p, c = np.nonzero(nxt[lin])
            parent = starts[t] + a + p
            if t + 1 < d:
                kid = starts[t + 1] + n_new + np.arange(p.size, dtype=np.int64)
                child[parent, c] = (kid - parent).astype(np.int32)
                new_coords.append(cells[p, c])
                n_new += p.size
            else:
                if dense:
                    xyz = cells[p, c]
                    vals = values[xyz[:, 0], xyz[:, 1], xyz[:, 2]]
                else:
                    vals = values[np.searchsorted(sparse_keys, lin[p, c])]
                vals = vals.astype(np.float32)
                if not np.isfinite(vals).all():
                    raise ValueError("values of occupied cells must be finite")
                if (vals[:, -1] < 0).any():
                    raise ValueError("sigma (values[..., -1]) of occupied cells must be >= 0")
                data[parent, c] = vals
        if t + 1 < d:
            coords = np.concatenate(new_coords) if new_coords else np.zeros((0, 3), np.int64)
            assert len(coords) == counts[t + 1]
    return Octree(child=child.reshape(n_nodes, 2, 2, 2), data=data.reshape(n_nodes, 2, 2, 2, dim),
                  offset=offset, invradius=invradius, data_format=data_format,
                  extra_data=extra, depth_limit=d - 1)


def _node_keys(depth: int, q: np.ndarray) -> np.ndarray:
    """int64 keys of node cubes ``q [M, 3]`` (coordinates < ``2^depth``), C order."""
    return (q[:, 0] << (2 * depth)) | (q[:, 1] << depth) | q[:, 2]


def tree_from_leaves(depths: Any, coords: Any, values: Any, center: Any = 0.0, radius: Any = 1.0,
                     data_format: str = "SH16", extra_data: Any = None) -> Octree:
    """Build the octree holding the given leaves, of any mix of depths.

    A leaf of cell depth ``c`` (as :attr:`Octree.depth_limit`: the root's cells have depth 0)
    sits at integer ``coords`` in ``[0, 2^(c+1))^3`` of the ``2^(c+1)`` grid over the box. Their
    ancestors become nodes; every other cell of those nodes is an empty leaf (zero data), so
    space that holds no given leaf stays as coarse as it can. Nodes are numbered breadth-first.

    Args:
        depths: int ``[M]`` cell depths (0 .. ``MAX_DEPTH``). coords: int ``[M, 3]``.
        values: float ``[M, D]`` the leaves' data (colour coefficients then σ >= 0).
        center, radius, data_format, extra_data: as :func:`tree_from_grid`.

    Returns:
        An :class:`Octree` with float32 data and ``depth_limit = max(depths)``.

    Raises:
        ValueError: bad shapes, coordinates outside their grid, a leaf inside another or
            given twice, non-finite values or σ < 0.
    """
    from .limits import MAX_DEPTH

    dep = np.asarray(depths, dtype=np.int64).reshape(-1)
    xyz = np.asarray(coords, dtype=np.int64).reshape(-1, 3)
    vals = np.asarray(values, dtype=np.float32)
    m = dep.shape[0]
    if xyz.shape[0] != m or vals.ndim != 2 or vals.shape[0] != m or m == 0:
        raise ValueError(f"need depths [M], coords [M, 3], values [M, D] with M >= 1, got "
                         f"{list(dep.shape)}, {list(xyz.shape)}, {list(vals.shape)}")
    if dep.min() < 0 or dep.max() > MAX_DEPTH:
        raise ValueError(f"leaf depths must be in [0, {MAX_DEPTH}]")
    if (xyz < 0).any() or (xyz >= (np.int64(2) << dep)[:, None]).any():
        raise ValueError("leaf coordinates must lie in [0, 2^(depth + 1)) per axis")
    if not np.isfinite(vals).all() or (vals[:, -1] < 0).any():
        raise ValueError("leaf values must be finite with sigma (the last channel) >= 0")
    extra = _check_format(data_format, int(vals.shape[1]), extra_data)
    d_max = int(dep.max())
    keys = []                                   # sorted node keys per node depth 0..d_max
    for t in range(d_max + 1):
        sel = dep >= t
        q = xyz[sel] >> (dep[sel] - t + 1)[:, None]
        keys.append(np.unique(_node_keys(t, q)))
    starts = np.concatenate([[0], np.cumsum([len(k) for k in keys])]).astype(np.int64)
    n_nodes = int(starts[-1])
    child = np.zeros((n_nodes, 8), dtype=np.int32)
    for t in range(1, d_max + 1):
        k = keys[t]
        q = np.stack([k >> (2 * t), (k >> t) & ((1 << t) - 1), k & ((1 << t) - 1)], -1)
        parent = starts[t - 1] + np.searchsorted(keys[t - 1], _node_keys(t - 1, q >> 1))
        slot = ((q[:, 0] & 1) << 2) | ((q[:, 1] & 1) << 1) | (q[:, 2] & 1)
        child[parent, slot] = (starts[t] + np.arange(len(k)) - parent).astype(np.int32)
    node = _leaf_nodes(dep, xyz, keys, starts)
    slot = ((xyz[:, 0] & 1) << 2) | ((xyz[:, 1] & 1) << 1) | (xyz[:, 2] & 1)
    flat = node * 8 + slot
    if (child.reshape(-1)[flat] != 0).any():
        raise ValueError("a leaf lies inside another leaf (a cell is both a leaf and a node)")
    if np.unique(flat).size != m:
        raise ValueError("a leaf is given twice")
    data = np.zeros((n_nodes * 8, vals.shape[1]), dtype=np.float32)
    data[flat] = vals
    offset, invradius = box_params(center, radius)
    return Octree(child=child.reshape(n_nodes, 2, 2, 2),
                  data=data.reshape(n_nodes, 2, 2, 2, vals.shape[1]), offset=offset,
                  invradius=invradius, data_format=data_format, extra_data=extra,
                  depth_limit=d_max)


def _leaf_nodes(dep: np.ndarray, xyz: np.ndarray, keys: list, starts: np.ndarray
                ) -> np.ndarray:
    """Index ``[M]`` of the node holding each leaf (the node at the leaf's own depth)."""
    node = np.empty(dep.shape[0], dtype=np.int64)
    for c in np.unique(dep):
        i = np.flatnonzero(dep == c)
        node[i] = starts[c] + np.searchsorted(keys[c], _node_keys(int(c), xyz[i] >> 1))
    return node


def _default_lobes(b: int, rng: np.random.Generator) -> np.ndarray:
    """``[b, 4]`` SG lobes: sharpness in [1, 5], unit axes from a Fibonacci sphere."""
    i = np.arange(b) + 0.5
    z = 1.0 - 2.0 * i / b
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    mu = np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)
    sharp = rng.uniform(1.0, 5.0, size=(b, 1))
    return np.concatenate([sharp, mu], -1).astype(np.float32)


def dense_tree(depth: int, data_format: str = "SH1", center: Any = 0.0, radius: Any = 1.0,
               values: Any = None, seed: int | None = None, extra_data: Any = None) -> Octree:
    """A fully refined tree: every leaf at ``depth`` (``(2^(depth+1))^3`` leaves), for tests.

    Args:
        depth: leaf depth >= 0 (0 = only the root node).
        values: ``[R, R, R, D]`` with ``R = 2^(depth+1)``; if None, zeros, or when ``seed`` is
            given random colours ~ N(0, 1) and σ ~ |N(0, 1)| * 4 / radius.
        extra_data: SG lobes ``[B, 4]``; for SG formats defaults to Fibonacci-sphere lobes.
    """
    if isinstance(depth, bool) or not isinstance(depth, (int, np.integer)) or not 0 <= depth <= 10:
        raise ValueError(f"depth must be an integer in 0..10, got {depth!r}")
    res = 1 << (int(depth) + 1)
    try:
        kind, b = parse_data_format(data_format)
        dim = expected_data_dim(data_format)
    except TreeFormatError as e:
        raise ValueError(str(e)) from None
    rng = np.random.default_rng(seed)
    if kind == "SG" and extra_data is None:
        extra_data = _default_lobes(b, rng)
    if values is None:
        values = np.zeros((res, res, res, dim), dtype=np.float32)
        if seed is not None:
            values[..., :-1] = rng.normal(size=(res, res, res, dim - 1))
            scale = 4.0 / float(np.max(np.broadcast_to(radius, (3,))))
            values[..., -1] = np.abs(rng.normal(size=(res, res, res))) * scale
    return tree_from_grid(values, np.ones((res, res, res), dtype=bool), center, radius,
                          data_format, extra_data)
