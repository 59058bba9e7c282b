"""Tree files: the native ``.npz`` format and the svox / volrend ``.npz`` layout.

Native file (``format_version`` 2; version 1 files, which have no ``ndc``, still load),
written by :func:`save_tree`:

=================  ==========================  ==============================================
key                dtype / shape               meaning
=================  ==========================  ==============================================
``format_version`` int64 scalar                2
``header``         unicode scalar (JSON)       data_format, sh_degree, basis_dim, data_dim,
                                               bbox, dtype, depth_limit, n_nodes, n_leaves,
                                               package version, ``ndc``: null or {width,
                                               height, fx, fy, near} (v2; see octree.ndc)
``child``          int32 ``[n, 2, 2, 2]``      relative child offsets (> 0), 0 = leaf
``data``           float16|32 ``[n,2,2,2,D]``  channel-major coefficients, σ last
``offset``         float64 ``[3]``             tree = offset + invradius3 * world
``invradius3``     float64 ``[3]``             0.5 / radius
``extra_data``     float32 ``[B, 4]``          SG lobes only
=================  ==========================  ==============================================

svox layout (:func:`export_svox` / :func:`import_svox`): keys ``child`` int32, ``data``
float16, ``data_dim``, ``data_format``, ``invradius3`` float32, ``offset`` float32,
``parent_depth`` int32 ``[n, 2]`` (packed parent cell ``node*8 + i*4 + j*2 + k``, node depth;
root ``[-1, 0]``), ``n_internal``, ``n_free``, ``depth_limit``, ``geom_resize_fact``, for
SG, ``extra_data`` and, for NDC trees, ``ndc_config`` float64 ``[5]`` (width, height, fx, fy,
near; an extra key svox and volrend ignore).

Every bad file raises ``TreeFormatError("<path>: <problem>")``, checked before anything is
returned; files are never unpickled and writes are atomic.
"""

from __future__ import annotations

import json
import os
from typing import Any

import numpy as np

from .._util import atomic_save_npz
from ..errors import TreeFormatError
from .._npz import NpzReader
from .check import expected_data_dim
from .limits import MAX_DEPTH
from .ndc import NDCSpace
from .tree import Octree, parse_data_format

__all__ = ["save_tree", "load_tree", "export_svox", "import_svox", "FORMAT_VERSION"]

FORMAT_VERSION = 2
READ_VERSIONS = (1, 2)       # 1: no "ndc" in the header (world-space trees)
_FP16_MAX = float(np.finfo(np.float16).max)
_SVOX_KEYS = ("child", "data", "offset")


# ---------------------------------------------------------------------- helpers
def _checked(tree: Octree, what: str) -> None:
    if not isinstance(tree, Octree):
        raise TypeError(f"{what}: expected an Octree, got {type(tree).__name__}")
    tree.check_integrity(f"{what}: tree")


def _to_fp16(data: np.ndarray, what: str) -> np.ndarray:
    # max and min, not max(abs(...)): no temporary as large as the tree's data
    peak = max(float(data.max()), -float(data.min())) if data.size else 0.0
    if peak > _FP16_MAX:
        raise ValueError(f"{what}: data values up to {peak:.6g} exceed the float16 range "
                         f"(max {_FP16_MAX:g}); save with precision='fp32' or rescale")
    return data.astype(np.float16)


def _finish(tree: Octree, keep_dtype: bool) -> Octree:
    if not keep_dtype and tree.data.dtype != np.float32:
        tree.data = tree.data.astype(np.float32)
    return tree


def _check_vec3(r: NpzReader, key: str, allow_scalar: bool = False) -> np.ndarray:
    shape, dt = r.shape(key), r.dtype(key)
    ok_shapes = ((3,), (), (1,)) if allow_scalar else ((3,),)
    if dt.kind not in "fiu" or shape not in ok_shapes:
        r.fail(f"{key!r} must be a float array of shape [3], got {dt} {list(shape)}")
    v = np.broadcast_to(r.read(key).astype(np.float64).reshape(-1), (3,)).copy()
    if not np.isfinite(v).all():
        r.fail(f"{key!r} has non-finite values {v.tolist()}")
    return v


def _check_tree_arrays(r: NpzReader, int_kinds: str, float_dtypes: tuple) -> tuple[int, int]:
    """Shapes/dtypes of ``child`` and ``data``; returns ``(n_rows, data_dim)``."""
    cs, cd = r.shape("child"), r.dtype("child")
    if cd.kind not in int_kinds or (int_kinds == "i" and cd != np.int32):
        r.fail(f"'child' must be int32, got {cd}")
    if len(cs) != 4 or cs[1:] != (2, 2, 2) or cs[0] < 1:
        r.fail(f"'child' must have shape [n_nodes >= 1, 2, 2, 2], got {list(cs)}")
    ds, dd = r.shape("data"), r.dtype("data")
    if dd not in float_dtypes:
        r.fail(f"'data' must be {'/'.join(str(np.dtype(t)) for t in float_dtypes)}, got {dd}")
    if len(ds) != 5 or ds[:4] != cs or ds[4] < 2:
        r.fail(f"'data' must have shape [n_nodes={cs[0]}, 2, 2, 2, data_dim >= 2], "
               f"got {list(ds)}")
    return cs[0], ds[4]


def _read_extra(r: NpzReader, data_format: str) -> np.ndarray | None:
    kind, b = parse_data_format(data_format)
    if kind != "SG":
        return None
    r.require("extra_data")
    shape, dt = r.shape("extra_data"), r.dtype("extra_data")
    if dt.kind != "f" or shape != (b, 4):
        r.fail(f"'extra_data' must be float [{b}, 4] for {data_format!r}, got {dt} {list(shape)}")
    return r.read("extra_data").astype(np.float32)


def _format(r: NpzReader, fmt: Any, data_dim: int) -> str:
    try:
        want = expected_data_dim(fmt)
    except TreeFormatError as e:
        r.fail(str(e))
    if want != data_dim:
        r.fail(f"data_dim {data_dim} does not match data_format {fmt!r} (expects {want})")
    return fmt


# ---------------------------------------------------------------------- native
def save_tree(tree: Octree, path: str | os.PathLike, precision: str = "fp32",
              compressed: bool = False) -> None:
    """Write ``tree`` to ``path`` in the native format (atomically; the name is used as is).

    Args:
        precision: ``"fp32"`` (lossless, the default) or ``"fp16"`` (half the size; raises
            ``ValueError`` if a value exceeds the float16 range). Recorded in the header.
        compressed: DEFLATE the archive (smaller, slower).
    Raises:
        TreeFormatError: the tree fails :meth:`Octree.check_integrity` (nothing is written).
    """
    from .. import __version__

    if precision not in ("fp16", "fp32"):
        raise ValueError(f"save_tree: precision must be 'fp16' or 'fp32', got {precision!r}")
    _checked(tree, f"save_tree({os.fspath(path)})")
    data = _to_fp16(tree.data, f"save_tree({os.fspath(path)})") if precision == "fp16" \
        else np.asarray(tree.data, dtype=np.float32)   # no copy of float32 data (GBs at 800²)
    header = {
        "format": "plenoctree-tree",
        "data_format": tree.data_format,
        "sh_degree": tree.sh_degree,
        "basis_dim": tree.basis_dim,
        "data_dim": tree.data_dim,
        "bbox": tree.bbox.tolist(),
        "dtype": str(data.dtype),
        "depth_limit": int(tree.depth_limit),
        "n_nodes": tree.n_nodes,
        "n_leaves": tree.n_leaves,
        "package_version": __version__,
        "ndc": None if tree.ndc is None else tree.ndc.to_json(),
    }
    arrays = dict(format_version=np.int64(FORMAT_VERSION), header=np.array(json.dumps(header)),
                  child=tree.child.astype(np.int32), data=data,
                  offset=tree.offset.astype(np.float64),
                  invradius3=tree.invradius.astype(np.float64))
    if tree.extra_data is not None:
        arrays["extra_data"] = tree.extra_data.astype(np.float32)
    atomic_save_npz(path, compressed=compressed, **arrays)


def _load_native(r: NpzReader, keep_dtype: bool) -> Octree:
    r.require("format_version", "header", "child", "data", "offset", "invradius3")
    version = r.scalar_int("format_version")
    if version not in READ_VERSIONS:
        r.fail(f"unknown format_version {version} (this plenoctree reads versions "
               f"{', '.join(map(str, READ_VERSIONS))}; a newer plenoctree may read it)")
    header = r.json("header")
    fmt, depth_limit = header.get("data_format"), header.get("depth_limit")
    if not isinstance(fmt, str):
        r.fail(f"header has no string 'data_format' (got {fmt!r})")
    if isinstance(depth_limit, bool) or not isinstance(depth_limit, int) or depth_limit < 0:
        r.fail(f"header 'depth_limit' must be an integer >= 0, got {depth_limit!r}")
    n, dim = _check_tree_arrays(r, "i", (np.float16, np.float32))
    _format(r, fmt, dim)
    if header.get("dtype", str(r.dtype("data"))) != str(r.dtype("data")):
        r.fail(f"header dtype {header.get('dtype')!r} does not match data dtype {r.dtype('data')}")
    for key in ("data_dim", "n_nodes"):
        if key in header and header[key] != (dim if key == "data_dim" else n):
            r.fail(f"header {key}={header[key]!r} does not match the arrays "
                   f"({dim if key == 'data_dim' else n})")
    offset, invradius = _check_vec3(r, "offset"), _check_vec3(r, "invradius3")
    extra = _read_extra(r, fmt)
    ndc = None
    if version >= 2 and header.get("ndc") is not None:
        try:
            ndc = NDCSpace.from_json(header["ndc"], "header 'ndc'")
        except TreeFormatError as e:
            r.fail(str(e))
    tree = Octree(child=r.read("child"), data=r.read("data"), offset=offset,
                  invradius=invradius, data_format=fmt, extra_data=extra,
                  depth_limit=depth_limit, ndc=ndc)
    tree.check_integrity(r.name)
    return _finish(tree, keep_dtype)


def load_tree(path: str | os.PathLike, keep_dtype: bool = False) -> Octree:
    """Load a tree file, native or svox layout (detected by its keys).

    Args:
        keep_dtype: keep the stored data dtype (float16 files stay float16); by default data
            is float32 in memory.
    Returns:
        A validated :class:`Octree` (``check_integrity`` passed).
    Raises:
        TreeFormatError: any problem with the file, naming the file and the problem.
    """
    with NpzReader(path) as r:
        if "format_version" in r:
            return _load_native(r, keep_dtype)
        if "quant_colors" in r or "quant_map" in r:
            r.fail("this is a compressed svox tree (quant_colors/quant_map); decompress it with "
                   "plenoctree.compression first")
        if all(k in r for k in _SVOX_KEYS):
            return _load_svox(r, keep_dtype)
        r.fail(f"not a tree file: needs 'format_version' (native) or {list(_SVOX_KEYS)} (svox); "
               f"found keys {r.keys()}")
    raise AssertionError("unreachable")


# ---------------------------------------------------------------------- svox
def export_svox(tree: Octree, path: str | os.PathLike) -> None:
    """Write ``tree`` in the svox / volrend layout (float16 data), atomically.

    Readable by ``svox.N3Tree.load`` and volrend. An NDC tree adds ``ndc_config`` (which they
    ignore; :func:`plenoctree.export.export_svox_file` also writes volrend's
    ``<stem>_poses_bounds.npy`` beside it). Raises ``ValueError`` if a value exceeds the
    float16 range, ``TreeFormatError`` if the tree is invalid (nothing is written).
    """
    what = f"export_svox({os.fspath(path)})"
    _checked(tree, what)
    n = tree.n_nodes
    flat = tree.child.reshape(-1)
    cells = np.flatnonzero(flat)
    parent_depth = np.zeros((n, 2), dtype=np.int32)
    parent_depth[0, 0] = -1
    parent_depth[cells // 8 + flat[cells], 0] = cells      # node*8 + i*4 + j*2 + k
    parent_depth[:, 1] = tree.node_depths()
    arrays = dict(child=tree.child.astype(np.int32), data=_to_fp16(tree.data, what),
                  data_dim=np.int64(tree.data_dim), data_format=np.array(tree.data_format),
                  invradius3=tree.invradius.astype(np.float32),
                  offset=tree.offset.astype(np.float32), parent_depth=parent_depth,
                  n_internal=np.int64(n), n_free=np.int64(0),
                  depth_limit=np.int64(tree.depth_limit), geom_resize_fact=np.float64(1.5))
    if tree.extra_data is not None:
        arrays["extra_data"] = tree.extra_data.astype(np.float32)
    if tree.ndc is not None:
        arrays["ndc_config"] = tree.ndc.as_array()
    atomic_save_npz(path, compressed=False, **arrays)


def _bfs_order(r: NpzReader, child: np.ndarray, allow_orphans: bool) -> np.ndarray | None:
    """Reachable nodes in breadth-first order, or None if the order is already the identity.

    svox offsets are relative and may in principle point backwards (reused free slots); any
    layout that forms a tree is accepted and renumbered. Shared nodes, cycles and (unless the
    file declares freed nodes) orphans are errors.
    """
    n = child.shape[0]
    flat = child.reshape(n, 8).astype(np.int64)
    cells = np.flatnonzero(flat)
    targets = cells // 8 + flat.reshape(-1)[cells]
    bad = np.flatnonzero((targets < 0) | (targets >= n))
    if bad.size:
        f = cells[bad[0]]
        r.fail(f"child[{f // 8}, {(f % 8) >> 2}, {(f >> 1) & 1}, {f & 1}] = "
               f"{flat.reshape(-1)[f]} points to node {targets[bad[0]]}, outside 0..{n - 1}")
    seen = np.zeros(n, dtype=bool)
    seen[0] = True
    levels = [np.zeros(1, dtype=np.int64)]
    total = 1
    while True:
        sub = flat[levels[-1]]
        p, c = np.nonzero(sub)
        if p.size == 0:
            break
        kids = levels[-1][p] + sub[p, c]
        if seen[kids].any() or np.unique(kids).size != kids.size:
            r.fail("child offsets do not form a tree (a node is reached twice: shared child "
                   "or cycle)")
        seen[kids] = True
        total += kids.size
        levels.append(kids)
        if len(levels) > MAX_DEPTH + 1:     # bounded work on a hostile chain of levels
            r.fail(f"node {int(kids[0])} has depth {len(levels) - 1}: the tree is deeper than "
                   f"MAX_DEPTH = {MAX_DEPTH}, the deepest cell depth every renderer supports")
    if total < n and not allow_orphans:
        orphan = int(np.flatnonzero(~seen)[0])
        r.fail(f"node {orphan} is not reachable from the root ({n - total} orphan nodes, "
               "but n_free = 0)")
    order = np.concatenate(levels)
    if total == n and (order == np.arange(n)).all():
        return None
    return order


def _renumber(child: np.ndarray, order: np.ndarray) -> np.ndarray:
    """Child offsets after keeping nodes ``order`` (old indices) as new nodes 0..len-1."""
    n_old = child.shape[0]
    new_index = np.full(n_old, -1, dtype=np.int64)
    new_index[order] = np.arange(order.size)
    flat = child.reshape(n_old, 8)[order].astype(np.int64)
    p, c = np.nonzero(flat)
    out = np.zeros_like(flat)
    out[p, c] = new_index[order[p] + flat[p, c]] - p
    return out.astype(np.int32).reshape(-1, 2, 2, 2)


def _load_svox(r: NpzReader, keep_dtype: bool) -> Octree:
    r.require(*_SVOX_KEYS)
    if "invradius3" not in r and "invradius" not in r:
        r.fail(f"missing keys ['invradius3'] (or legacy 'invradius'); found {r.keys()}")
    cap, dim = _check_tree_arrays(r, "iu", (np.float16, np.float32, np.float64))
    if "data_dim" in r and r.scalar_int("data_dim") != dim:
        r.fail(f"data_dim {r.scalar_int('data_dim')} does not match data.shape[-1] = {dim}")
    n = r.scalar_int("n_internal") if "n_internal" in r else cap
    if not 1 <= n <= cap:
        r.fail(f"n_internal = {n} must be in 1..{cap} (the array capacity)")
    n_free = r.scalar_int("n_free") if "n_free" in r else 0
    if n_free < 0:
        r.fail(f"n_free = {n_free} is negative")
    if "parent_depth" in r:
        ps, pd = r.shape("parent_depth"), r.dtype("parent_depth")
        if pd.kind not in "iu" or len(ps) != 2 or ps[1] != 2 or ps[0] != cap:
            r.fail(f"'parent_depth' must be int [capacity={cap}, 2], got {pd} {list(ps)}")
    if "data_format" in r:
        fmt = r.scalar_str("data_format")
        if fmt.startswith("ASG"):
            r.fail(f"data_format {fmt!r} (anisotropic SG) is not supported")
    else:
        b = (dim - 1) // 3
        if (dim - 1) % 3 or b not in (1, 4, 9, 16, 25):
            r.fail(f"no data_format and data_dim {dim} is not 3*B+1 for an SH basis count B "
                   "in (1, 4, 9, 16, 25); cannot infer the format")
        fmt = f"SH{b}"
    _format(r, fmt, dim)
    depth_limit = r.scalar_int("depth_limit") if "depth_limit" in r else -1
    if "depth_limit" in r and depth_limit < 0:
        r.fail(f"depth_limit = {depth_limit} is negative")
    # svox's depth_limit only caps future refinement: clamp it to what our renderers support
    # (the tree's actual depth is still checked against MAX_DEPTH by check_integrity).
    depth_limit = min(depth_limit, MAX_DEPTH)
    offset = _check_vec3(r, "offset", allow_scalar=True)
    key = "invradius3" if "invradius3" in r else "invradius"
    invradius = _check_vec3(r, key, allow_scalar=True)
    if not (invradius > 0).all():
        r.fail(f"{key!r} must be > 0, got {invradius.tolist()}")
    extra = _read_extra(r, fmt)
    ndc = None
    if "ndc_config" in r:
        shape, dt = r.shape("ndc_config"), r.dtype("ndc_config")
        if dt.kind not in "fiu" or shape != (5,):
            r.fail(f"'ndc_config' must be 5 numbers (width, height, fx, fy, near), got {dt} "
                   f"{list(shape)}")
        try:
            ndc = NDCSpace.from_array(r.read("ndc_config"))
        except TreeFormatError as e:
            r.fail(str(e))
    child_all = r.read("child")
    if child_all.dtype != np.int32:
        if np.abs(child_all.astype(np.int64)).max() >= cap:
            r.fail("child offsets exceed the node count")
        child_all = child_all.astype(np.int32)
    child = child_all[:n]
    data = r.read("data")[:n]
    order = _bfs_order(r, child, allow_orphans=n_free > 0)
    if order is not None:
        child, data = _renumber(child, order), data[order]
    data = np.ascontiguousarray(data)
    if not np.isfinite(data).all():
        bad = np.argwhere(~np.isfinite(data))[0].tolist()
        r.fail(f"data{bad} is not finite")
    sigma = data[..., -1]
    np.maximum(sigma, 0, out=sigma)     # svox/volrend render σ <= 0 as empty space
    tree = Octree(child=child, data=data, offset=offset, invradius=invradius, data_format=fmt,
                  extra_data=extra, depth_limit=depth_limit, ndc=ndc)
    tree.check_integrity(r.name)
    return _finish(tree, keep_dtype)


def import_svox(path: str | os.PathLike, keep_dtype: bool = False) -> Octree:
    """Load a tree written by svox (``N3Tree.save``) or :func:`export_svox`.

    Accepts legacy files (scalar ``invradius``, no ``data_format`` → SH inferred from
    ``data_dim``), trims capacity beyond ``n_internal``, drops freed nodes (``n_free > 0``),
    renumbers nodes breadth-first, clamps negative σ to 0 (svox renders them as empty) and
    ``depth_limit`` to ``MAX_DEPTH`` (a tree deeper than ``MAX_DEPTH`` is an error).
    ``parent_depth`` is redundant with ``child`` and only its shape is checked.

    Raises:
        TreeFormatError: any problem with the file, naming the file and the problem.
    """
    with NpzReader(path) as r:
        if "format_version" in r:
            r.fail("this is a native plenoctree file, not an svox tree; use load_tree()")
        return _load_svox(r, keep_dtype)
