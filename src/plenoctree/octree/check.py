"""Validation of an :class:`~plenoctree.octree.tree.Octree` (``Octree.check_integrity``).

Every problem raises :class:`~plenoctree.errors.TreeFormatError` with the message
``"<name>: <problem>"`` naming the first offending entry, so the same checker serves in-memory
trees (``name="tree"``) and loaded files (``name=<path>``).
"""

from __future__ import annotations

import weakref
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import TreeFormatError
from .limits import MAX_ABS_BOX, MAX_ABS_VALUE, MAX_DEPTH
from .ndc import NDCSpace
from .tree import parse_data_format

if TYPE_CHECKING:
    from .tree import Octree

__all__ = ["check_tree", "check_child", "check_child_cached", "check_box", "expected_data_dim"]

_CHUNK_NODES = 1 << 16     # data is checked in blocks of this many nodes (bounded temporaries)


def expected_data_dim(data_format: str) -> int:
    """Values per cell implied by ``data_format``: ``3 * basis_dim + 1`` (RGBA: 4)."""
    kind, n = parse_data_format(data_format)
    return 4 if kind == "RGBA" else 3 * n + 1


def _fail(name: str, problem: str) -> None:
    raise TreeFormatError(f"{name}: {problem}")


def _cell(flat_index: int) -> str:
    node, c = divmod(int(flat_index), 8)
    return f"[{node}, {c >> 2}, {(c >> 1) & 1}, {c & 1}]"


def check_box(offset: np.ndarray, invradius: np.ndarray, name: str = "tree") -> None:
    """``offset``/``invradius`` (float ``[3]``, finite) within the bounds of ``MAX_ABS_BOX``.

    ``invradius > 0``, ``1 / MAX_ABS_BOX <= invradius <= MAX_ABS_BOX`` and
    ``|offset| <= MAX_ABS_BOX`` on every axis: beyond them the world <-> tree transform has no
    precision left and rays stop advancing.
    """
    inv = np.asarray(invradius, dtype=np.float64)
    if not (inv > 0).all():
        _fail(name, f"invradius must be > 0 on every axis, got {inv.tolist()}")
    if not ((inv <= MAX_ABS_BOX) & (inv >= 1.0 / MAX_ABS_BOX)).all():
        _fail(name, f"invradius {inv.tolist()} is outside [{1.0 / MAX_ABS_BOX:g}, "
                    f"{MAX_ABS_BOX:g}] (tree box radius 0.5 / invradius out of range)")
    off = np.asarray(offset, dtype=np.float64)
    if not (np.abs(off) <= MAX_ABS_BOX).all():
        _fail(name, f"offset {off.tolist()} is outside [-{MAX_ABS_BOX:g}, {MAX_ABS_BOX:g}]")


def _check_arrays(tree: Octree, name: str) -> int:
    """Types, shapes and format fields; returns n_nodes."""
    child, data = tree.child, tree.data
    if not isinstance(child, np.ndarray) or child.dtype != np.int32:
        _fail(name, f"child must be an int32 array, got {getattr(child, 'dtype', type(child))}")
    if child.ndim != 4 or child.shape[1:] != (2, 2, 2):
        _fail(name, f"child must have shape [n_nodes, 2, 2, 2], got {list(child.shape)}")
    n = child.shape[0]
    if n < 1:
        _fail(name, "tree has no nodes (child has 0 rows; the root node is required)")
    if not isinstance(data, np.ndarray) or data.dtype not in (np.float16, np.float32, np.float64):
        _fail(name, f"data must be a float16/32/64 array, got {getattr(data, 'dtype', type(data))}")
    if data.ndim != 5 or data.shape[:4] != (n, 2, 2, 2):
        _fail(name, f"data must have shape [n_nodes={n}, 2, 2, 2, data_dim], "
                    f"got {list(data.shape)}")
    try:
        want = expected_data_dim(tree.data_format)
    except TreeFormatError as e:
        _fail(name, str(e))
    if data.shape[4] != want:
        _fail(name, f"data_dim {data.shape[4]} does not match data_format {tree.data_format!r} "
                    f"(expects {want})")
    for key in ("offset", "invradius"):
        v = getattr(tree, key)
        if not isinstance(v, np.ndarray) or v.shape != (3,) or v.dtype.kind != "f":
            _fail(name, f"{key} must be a float array of shape [3], got "
                        f"{getattr(v, 'dtype', type(v))} {list(getattr(v, 'shape', ()))}")
        if not np.isfinite(v).all():
            _fail(name, f"{key} has non-finite values {v.tolist()}")
    check_box(tree.offset, tree.invradius, name)
    kind, b = parse_data_format(tree.data_format)
    extra = tree.extra_data
    if kind == "SG":
        if not isinstance(extra, np.ndarray) or extra.shape != (b, 4):
            _fail(name, f"data_format {tree.data_format!r} needs extra_data of shape [{b}, 4] "
                        f"(sharpness, mu_x, mu_y, mu_z), got "
                        f"{None if extra is None else list(np.shape(extra))}")
        if not np.isfinite(extra).all():
            _fail(name, "extra_data has non-finite values")
        _check_sg_lobes(extra, name)
    elif extra is not None:
        _fail(name, f"extra_data must be None for data_format {tree.data_format!r}, got shape "
                    f"{list(np.shape(extra))}")
    return n


def _check_sg_lobes(extra: np.ndarray, name: str) -> None:
    """SG ``extra_data [B, 4]`` (λ, μ): sharpness in ``[0, MAX_SG_SHARPNESS]``, unit axes."""
    from .limits import MAX_SG_SHARPNESS, SG_AXIS_TOL

    lam = np.asarray(extra[:, 0], dtype=np.float64)
    bad = np.flatnonzero(~((lam >= 0) & (lam <= MAX_SG_SHARPNESS)))
    if bad.size:
        _fail(name, f"extra_data[{bad[0]}, 0]: SG lobe sharpness {lam[bad[0]]:g} is outside "
                    f"[0, {MAX_SG_SHARPNESS:g}]")
    norm = np.linalg.norm(np.asarray(extra[:, 1:4], dtype=np.float64), axis=1)
    bad = np.flatnonzero(~(np.abs(norm - 1.0) <= SG_AXIS_TOL))
    if bad.size:
        _fail(name, f"extra_data[{bad[0]}, 1:4]: SG lobe axis has length {norm[bad[0]]:g}, not "
                    f"1 (within {SG_AXIS_TOL:g})")


def check_child(child: np.ndarray, depth_limit: int, name: str = "tree") -> None:
    """Check the topology of a ``child`` array (int ``[n, 2, 2, 2]``, n >= 1).

    Offsets >= 0 and pointing inside the array; exactly one parent per non-root node (with
    positive offsets: no cycles, no orphans); cell depth <= ``depth_limit`` <= ``MAX_DEPTH``.
    Work is bounded: the level walk stops after ``MAX_DEPTH + 1`` levels. Shared by
    :func:`check_tree` and the compressed tree's ``validate``.
    """
    if isinstance(depth_limit, bool) or not isinstance(depth_limit, (int, np.integer)) \
            or depth_limit < 0:
        _fail(name, f"depth_limit must be an integer >= 0, got {depth_limit!r}")
    n = child.shape[0]
    flat = child.reshape(-1)
    neg = np.flatnonzero(flat < 0)
    if neg.size:
        f = neg[0]
        _fail(name, f"child{_cell(f)} = {flat[f]} is negative ({neg.size} negative offsets; "
                    "child nodes must come after their parent, offset > 0, or 0 for a leaf)")
    cells = np.flatnonzero(flat)
    targets = cells // 8 + flat[cells].astype(np.int64)
    bad = np.flatnonzero(targets >= n)
    if bad.size:
        f = cells[bad[0]]
        _fail(name, f"child{_cell(f)} = {flat[f]} points to node {targets[bad[0]]}, past the last "
                    f"node {n - 1} ({bad.size} out-of-range offsets)")
    parents = np.bincount(targets, minlength=n)
    shared = np.flatnonzero(parents > 1)
    if shared.size:
        _fail(name, f"node {shared[0]} has {parents[shared[0]]} parents ({shared.size} shared "
                    "nodes; every non-root node must have exactly one parent)")
    orphans = np.flatnonzero(parents[1:] == 0) + 1
    if orphans.size:
        _fail(name, f"node {orphans[0]} has no parent ({orphans.size} orphan nodes; every "
                    "non-root node must have exactly one parent)")
    # Offsets > 0 and one parent each: every node is reachable from the root, no cycles.
    # Walk level by level; nodes of depth t hold cells of depth t.
    rows = child.reshape(n, 8)
    level = np.zeros(1, dtype=np.int64)
    for t in range(1, MAX_DEPTH + 2):
        sub = rows[level]
        p, c = np.nonzero(sub)
        if p.size == 0:
            break
        level = level[p] + sub[p, c].astype(np.int64)
        if t > min(depth_limit, MAX_DEPTH):
            what = (f"exceeds MAX_DEPTH = {MAX_DEPTH}, the deepest cell depth every renderer "
                    "supports" if t > MAX_DEPTH else f"exceeds depth_limit {depth_limit}")
            _fail(name, f"node {int(level[0])} has depth {t}: the tree is at least {t + 1} "
                        f"levels deep and {what}")
    if depth_limit > MAX_DEPTH:
        _fail(name, f"depth_limit {depth_limit} exceeds MAX_DEPTH = {MAX_DEPTH} (the deepest "
                    "cell depth every renderer supports)")


def _check_topology(tree: Octree, name: str, n: int) -> None:
    check_child(tree.child, tree.depth_limit, name)


def _check_values(tree: Octree, name: str, n: int) -> None:
    """Finite data and σ >= 0 in every cell (checked in blocks of nodes)."""
    for start in range(0, n, _CHUNK_NODES):
        block = tree.data[start:start + _CHUNK_NODES]
        if block.dtype == np.float16:                   # float16 cannot exceed the bound
            finite = np.isfinite(block)
        else:
            finite = np.abs(block) <= MAX_ABS_VALUE    # False for NaN and inf too
        if not finite.all():
            f = np.argwhere(~finite)[0]
            v = block[tuple(f)]
            what = "is not finite" if not np.isfinite(v) else \
                f"exceeds MAX_ABS_VALUE = {MAX_ABS_VALUE:g} in magnitude (renders NaN)"
            _fail(name, f"data[{start + f[0]}, {f[1]}, {f[2]}, {f[3]}, {f[4]}] = {v} {what}")
        sig = block[..., -1]
        if (sig < 0).any():
            f = np.argwhere(sig < 0)[0]
            _fail(name, f"sigma (data[..., -1]) at cell [{start + f[0]}, {f[1]}, {f[2]}, {f[3]}] "
                        f"= {sig[tuple(f)]} is negative (sigma must be >= 0)")


def check_tree(tree: Octree, name: str = "tree") -> None:
    """Raise ``TreeFormatError("<name>: <problem>")`` unless ``tree`` is a valid octree.

    Checks, in order: ``child`` int32 ``[n, 2, 2, 2]`` with n >= 1; ``data`` float
    ``[n, 2, 2, 2, D]`` with D matching ``data_format``; ``offset``/``invradius`` finite ``[3]``,
    ``invradius`` and ``offset`` within :func:`check_box`; SG ``extra_data [B, 4]`` finite (None otherwise); then
    :func:`check_child`: ``0 <= depth_limit <= MAX_DEPTH``, child offsets >= 0 and pointing
    inside the array, every non-root node has exactly one parent (which, with positive
    offsets, rules out cycles and orphans), cell depth <= ``depth_limit``;
    data finite with ``|value| <= MAX_ABS_VALUE``; σ >= 0; ``ndc`` an ``NDCSpace`` or None.
    """
    n = _check_arrays(tree, name)
    ndc = getattr(tree, "ndc", None)
    if ndc is not None and not isinstance(ndc, NDCSpace):
        raise TreeFormatError(f"{name}: ndc must be an NDCSpace or None, got {type(ndc).__name__}")
    _check_topology(tree, name, n)
    _check_values(tree, name, n)


# Trees whose topology passed check_child, with the fingerprint it passed with.
_CHECKED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _fingerprint(tree: Any) -> tuple:
    """Identity and version of ``tree.child``: changes when the array is replaced or edited.

    numpy arrays carry no version counter, so their fingerprint includes the wrapped sum of
    the offsets (one cheap pass; any edit that could break the tree changes it in practice).
    torch tensors carry ``_version`` (bumped by every in-place op).
    """
    child = tree.child
    if hasattr(child, "_version") and hasattr(child, "data_ptr"):      # torch tensor
        return ("torch", id(child), child.data_ptr(), tuple(child.shape), child._version)
    arr = np.asarray(child)
    return ("numpy", id(child), arr.__array_interface__["data"][0], arr.shape, arr.strides,
            str(arr.dtype), int(arr.sum(dtype=np.int64)))


def check_child_cached(tree: Any, name: str = "tree") -> None:
    """:func:`check_child` on ``tree.child``, once per tree object and version of ``child``.

    For renderers that receive in-memory trees on every frame: the first call does the full
    (bounded, vectorised) check, later calls only compare a fingerprint. Depth is checked
    against ``MAX_DEPTH`` (what the renderers need), not the tree's own ``depth_limit``.
    Raises ``TreeFormatError``.
    """
    key = _fingerprint(tree)
    try:
        if _CHECKED.get(tree) == key:
            return
    except TypeError:           # not weak-referenceable / unhashable: check every time
        pass
    child = tree.child
    if hasattr(child, "detach"):
        child = child.detach().cpu().numpy()
    child = np.asarray(child)
    if child.dtype.kind not in "iu" or child.ndim != 4 or child.shape[1:] != (2, 2, 2) \
            or child.shape[0] < 1:
        _fail(name, f"child must be an int array of shape [n_nodes >= 1, 2, 2, 2], got "
                    f"{child.dtype} {list(child.shape)}")
    check_child(child, MAX_DEPTH, name)
    try:
        _CHECKED[tree] = key
    except TypeError:
        pass
