"""Adaptive refinement of a PlenOctree against the radiance field it was made from.

An extracted tree stores one value per leaf of one size. Where the field varies inside a leaf
(a surface cuts it, a texture edge crosses it) that value is a poor stand-in, and where it does
not, a smaller tree would do. :func:`refine_tree` makes the tree adaptive:

- **score** every non-empty leaf by how badly its value represents the field inside it:
  ``S`` random samples of the field in the leaf give the *spread*
  ``e = mean_s |α_s - ᾱ| + mean_s α_s · mean_ch |c_s - c̄|`` where ``α = 1 - exp(-σ h)`` is the
  opacity of the leaf's side ``h`` (world units) at a sample's σ, ``ᾱ`` that of the mean σ, and
  ``c`` the base colour (``sigmoid(C0 · k_0)`` for SH, the sigmoid of the channel's mean
  coefficient otherwise) — both are errors in the [0, 1] units of a rendered pixel;
- **subdivide** the leaves with ``e ≥ threshold`` (the worst first, at most ``max_fraction`` of
  the scored leaves per pass, never past ``max_depth``): each becomes a node whose 8 children
  get the mean of ``S`` field samples in their own box (as extraction does);
- **merge** nodes whose 8 children are leaves that agree (``max |α_i - ᾱ| + |c_i - c̄|`` below
  ``merge_tol``; all-empty siblings always agree) into one leaf holding their mean.

Leaves whose stored σ is 0 are never scored: extraction zeroes what the training views find
hidden (matter behind surfaces, floaters), and refinement must not bring it back. The result
is a valid svox-layout tree of mixed depths, nodes renumbered breadth-first
(``check_integrity`` holds).

:func:`refine` is the ``plenoctree refine`` command: a tree file + the NeRF-SH run it came from.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .._bounds import check_bounds
from .._util import atomic_save_json, progress
from ..errors import ConfigError
from ..sh import SH_C0
from ..octree.limits import MAX_DEPTH
from . import device_sampling
from .sampling import AVERAGING, SampleOptions, average_samples

__all__ = ["RefineConfig", "RefineOptions", "RefineResult", "refine", "refine_tree",
           "leaf_spread", "subdivide_leaves", "merge_leaves", "compact_tree", "field_error",
           "MAX_DEPTH"]

logger = logging.getLogger(__name__)

_COPY_NODES = 1 << 13
"""Old nodes copied per block when a subdivided tree is assembled (13 MB of SH16 float32)."""

_CELL = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=np.float64)


# ---------------------------------------------------------------------- sampling and scores
def _base_colour(coeffs: np.ndarray, data_format: str, basis_dim: int) -> np.ndarray:
    """``[..., 3]`` base colour in [0, 1] from channel-major coefficients ``[..., 3 B]``."""
    c = coeffs.reshape(coeffs.shape[:-1] + (3, basis_dim))
    raw = SH_C0 * c[..., 0] if data_format.startswith("SH") else c.mean(axis=-1)
    return 1.0 / (1.0 + np.exp(-raw))


def _box_stats(field_: Any, lo: np.ndarray, size: np.ndarray, tree: Any, samples: int,
               rng: Any, averaging: str = "mean") -> tuple[np.ndarray, np.ndarray]:
    """Average field value ``[M, D]`` (σ ≥ 0 last; ``averaging`` as in
    :func:`~plenoctree.convert.sampling.average_samples`) and spread ``[M]`` of ``samples``
    uniform random points in each world box ``lo [M, 3] + [0, size [M, 3]]``; ``tree`` gives
    the value layout (``data_format``, ``basis_dim``, ``data_dim``). On the field's device
    where :func:`~.device_sampling.sampling_device` says so, with ``rng`` from
    :func:`~.device_sampling.make_rng` (numpy's on the host, a torch generator there)."""
    if device_sampling.sampling_device(field_) is not None:
        return device_sampling.box_stats_device(field_, lo, size, samples, rng, tree, averaging)
    fmt, basis_dim, dim = tree.data_format, tree.basis_dim, tree.data_dim
    m = lo.shape[0]
    pts = (lo[:, None, :] + rng.random((m, samples, 3)) * size[:, None, :]).astype(np.float32)
    sigma, coeffs = field_.query(pts.reshape(-1, 3))
    vals = np.concatenate([np.asarray(coeffs, np.float32),
                           np.asarray(sigma, np.float32).reshape(-1, 1)], axis=1)
    if vals.shape != (m * samples, dim):
        raise ConfigError(f"field.query returned {vals.shape[1]} values per point; the tree "
                          f"({fmt}) needs {dim}")
    vals[~np.isfinite(vals)] = 0.0
    vals = vals.reshape(m, samples, dim)
    np.maximum(vals[..., -1], 0.0, out=vals[..., -1])
    mean = average_samples(vals, size.mean(axis=1), averaging)
    return mean, _spread(vals, mean, size.mean(axis=1), fmt, basis_dim)


def _spread(vals: np.ndarray, mean: np.ndarray, h: np.ndarray, fmt: str,
            basis_dim: int) -> np.ndarray:
    """The spread score ``[M]`` of samples ``vals [M, S, D]`` around ``mean [M, D]``
    (leaf side ``h [M]``, world units); see the module docstring."""
    a = 1.0 - np.exp(-vals[..., -1] * h[:, None])
    a_mean = 1.0 - np.exp(-mean[:, -1] * h)
    c = _base_colour(vals[..., :-1], fmt, basis_dim)
    c_mean = _base_colour(mean[:, :-1], fmt, basis_dim)
    e_sigma = np.abs(a - a_mean[:, None]).mean(axis=1)
    e_col = (a * np.abs(c - c_mean[:, None, :]).mean(axis=-1)).mean(axis=1)
    return (e_sigma + e_col).astype(np.float32)


def _leaf_boxes(tree: Any) -> tuple[tuple[np.ndarray, ...], np.ndarray, np.ndarray, np.ndarray]:
    """``((node, i, j, k), lo_world [n, 3], size_world [n, 3], depth [n])`` of every leaf."""
    idx = tree.leaf_indices()
    depth, corner, size = tree._leaf_geometry()
    lo = tree.tree_to_world(corner)
    return idx, lo, size[:, None] / tree.invradius, depth


def _blocks(m: int, per_box: int, chunk: int):
    step = max(1, chunk // max(1, per_box))
    for s in range(0, m, step):
        yield s, min(m, s + step)


def leaf_spread(tree: Any, field_: Any, samples: int = 8, seed: int = 0, chunk: int = 1 << 17,
                leaves: np.ndarray | None = None, show_progress: bool | None = False
                ) -> np.ndarray:
    """Spread score ``[len(leaves)]`` (float32, pixel units) of the leaves ``leaves`` (indices
    into :meth:`~plenoctree.octree.Octree.leaf_indices` order; default all)."""
    _, lo, size, _ = _leaf_boxes(tree)
    sel = np.arange(lo.shape[0]) if leaves is None else np.asarray(leaves, np.int64)
    rng = device_sampling.make_rng(field_, seed)
    out = np.zeros(sel.size, np.float32)
    with progress(total=sel.size, desc="scoring", unit="leaf", unit_scale=True,
                  disable=None if show_progress is None else not show_progress) as bar:
        for s, e in _blocks(sel.size, samples, chunk):
            b = sel[s:e]
            _, out[s:e] = _box_stats(field_, lo[b], size[b], tree, samples, rng)
            bar.update(e - s)
    return out


def field_error(tree: Any, field_: Any, n_points: int = 200_000, seed: int = 1,
                box: np.ndarray | None = None, h: float | None = None) -> float:
    """Mean rendering-unit error of ``tree`` against ``field_`` at random points of ``box``
    (default the tree's box): ``mean |α_tree - α_field| + α_field · |c_tree - c_field|``
    with the opacity ``α = 1 - exp(-σ h)`` over a length ``h`` (world units; default the
    tree's finest leaf side — pass the same ``h`` when comparing two trees).

    Points where the tree stores σ = 0 and the field is dense are counted too, so a tree
    cannot lower its error by dropping content."""
    rng = np.random.default_rng(seed)
    b = np.asarray(tree.bbox if box is None else box, np.float64)
    pts = (b[0] + rng.random((int(n_points), 3)) * (b[1] - b[0])).astype(np.float32)
    if h is None:
        h = float(np.min(tree.leaf_sizes()[:, 0])) if tree.n_leaves else 1.0
    tv = tree.query(pts).astype(np.float32)
    sig, co = field_.query(pts)
    fv = np.concatenate([np.asarray(co, np.float32), np.asarray(sig, np.float32)[:, None]], 1)
    fv[~np.isfinite(fv)] = 0.0
    fv[:, -1] = np.maximum(fv[:, -1], 0.0)
    at, af = 1.0 - np.exp(-tv[:, -1] * h), 1.0 - np.exp(-fv[:, -1] * h)
    ct = _base_colour(tv[:, :-1], tree.data_format, tree.basis_dim)
    cf = _base_colour(fv[:, :-1], tree.data_format, tree.basis_dim)
    return float(np.mean(np.abs(at - af) + af * np.abs(ct - cf).mean(axis=-1)))


# ---------------------------------------------------------------------- structure edits
def _bfs_order(child: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Breadth-first renumbering of a node array ``child [n, 2, 2, 2]`` (relative offsets).

    Returns ``(order, new_child)``: ``order [n']`` the old index of each new node (a level's
    nodes ordered by parent, then cell ``i, j, k``, as the builders do; unreachable nodes are
    left out) and ``new_child [n', 2, 2, 2]`` int32 offsets in the new numbering."""
    n = child.shape[0]
    flat = child.reshape(n, 8).astype(np.int64)
    levels = [np.zeros(1, np.int64)]
    while True:
        sub = flat[levels[-1]]
        p, c = np.nonzero(sub > 0)
        if p.size == 0:
            break
        levels.append(levels[-1][p] + sub[p, c])
    order = np.concatenate(levels)
    new = np.full(n, -1, np.int64)
    new[order] = np.arange(order.size)
    ch = flat[order]
    tgt = np.where(ch > 0, order[:, None] + ch, 0)
    newch = np.where(ch > 0, new[tgt] - np.arange(order.size)[:, None], 0)
    return order, newch.astype(np.int32).reshape(-1, 2, 2, 2)


def compact_tree(tree: Any) -> Any:
    """The same tree with nodes renumbered breadth-first from the root (a level's nodes ordered
    by parent, then cell ``i, j, k``, as the builders do); unreachable nodes are dropped."""
    order, child = _bfs_order(tree.child)
    return dataclasses.replace(tree, child=child, data=np.ascontiguousarray(tree.data[order]),
                               depth_limit=int(tree.depth_limit))


def _leaf_sigma(tree: Any) -> np.ndarray:
    """σ of every leaf ``[n_leaves]`` (leaf order) without copying the other channels."""
    return tree.data[..., -1][tree.child == 0]


def subdivide_leaves(tree: Any, leaves: np.ndarray, field_: Any, samples: int = 8,
                     seed: int = 0, chunk: int = 1 << 17, show_progress: bool | None = False,
                     averaging: str = "mean") -> tuple[Any, np.ndarray]:
    """Split leaves ``leaves`` (indices in ``leaf_indices`` order) into 8 children each, valued
    by the average (``averaging``: "mean" or "opacity", as extraction's) of ``samples`` field
    samples in each child's box.

    Returns ``(new tree, spread [8 M] of the new children)``; the tree is renumbered
    breadth-first and its ``depth_limit`` raised to its new depth when needed.
    """
    leaves = np.unique(np.asarray(leaves, np.int64))
    (node, i, j, k), lo, size, depth = _leaf_boxes(tree)
    if leaves.size == 0:
        return tree, np.zeros(0, np.float32)
    new_depth = int(depth[leaves].max()) + 1
    if new_depth > MAX_DEPTH:
        raise ConfigError(f"subdividing would create cells of depth {new_depth} > the depth "
                          f"limit {MAX_DEPTH}")
    vals, spread = _child_values(tree, lo[leaves], size[leaves], field_, SampleOptions(
        samples=samples, chunk=chunk, seed=seed, averaging=averaging,
        show_progress=show_progress))
    out = _with_children(tree, (node[leaves], i[leaves], j[leaves], k[leaves]), vals,
                         max(int(tree.depth_limit), new_depth))
    del vals
    # children keep their order through compaction only per level; recompute their spread order
    return out, _children_spread_order(tree, out, leaves, spread)


def _child_values(tree: Any, lo: np.ndarray, size: np.ndarray, field_: Any,
                  opts: SampleOptions) -> tuple[np.ndarray, np.ndarray]:
    """Values ``[8 M, data_dim]`` float32 and spread ``[8 M]`` of the children of the M leaves
    whose boxes are ``lo, size [M, 3]`` (world units; order: leaf, then cell ``i, j, k``),
    each from ``opts.samples`` field samples (``opts.seed``, ``opts.chunk``, ``opts.averaging``;
    the projection options are unused)."""
    m, dim = lo.shape[0], tree.data_dim
    samples, show_progress = opts.samples, opts.show_progress
    half = size / 2.0
    clo = (lo[:, None, :] + _CELL[None] * half[:, None, :]).reshape(-1, 3)
    chalf = np.repeat(half, 8, axis=0)
    vals = np.empty((8 * m, dim), np.float32)
    spread = np.empty(8 * m, np.float32)
    rng = device_sampling.make_rng(field_, opts.seed)
    with progress(total=8 * m, desc="subdividing", unit="cell", unit_scale=True,
                  disable=None if show_progress is None else not show_progress) as bar:
        for s, e in _blocks(8 * m, samples, opts.chunk):
            vals[s:e], spread[s:e] = _box_stats(field_, clo[s:e], chalf[s:e], tree, samples,
                                                rng, opts.averaging)
            bar.update(e - s)
    return vals, spread


def _with_children(tree: Any, cells: tuple[np.ndarray, ...], vals: np.ndarray,
                   depth_limit: int) -> Any:
    """``tree`` with the leaf cells ``cells = (node, i, j, k)`` (M each) turned into nodes whose
    8 cells hold ``vals [8 M, data_dim]`` (order: leaf, then cell), renumbered breadth-first.

    Equal to appending the new nodes and calling :func:`compact_tree` (tested), but the data are
    written once, straight to their new places: the concatenated intermediate held the
    refinement's memory peak (three tree-sized arrays at lego 800²). Old nodes are copied in
    blocks of ``_COPY_NODES``; unreachable ones are dropped."""
    pn, pi, pj, pk = cells
    n, m = tree.n_nodes, pn.size
    child = np.concatenate([tree.child, np.zeros((m, 2, 2, 2), np.int32)])
    child[pn, pi, pj, pk] = (n + np.arange(m) - pn).astype(np.int32)
    order, child = _bfs_order(child)
    pos = np.full(n + m, -1, np.int64)
    pos[order] = np.arange(order.size)
    data = np.empty((order.size, 2, 2, 2, tree.data_dim), tree.data.dtype)
    for s in range(0, n, _COPY_NODES):
        p = pos[s:min(s + _COPY_NODES, n)]
        ok = p >= 0
        data[p[ok]] = tree.data[s:s + _COPY_NODES][ok]
    data[pos[n:]] = vals.reshape(m, 2, 2, 2, -1)      # cast to the tree's dtype
    data[pos[pn], pi, pj, pk] = 0                     # the split cells are inner now
    return dataclasses.replace(tree, child=child, data=data, depth_limit=int(depth_limit))


def _children_spread_order(old: Any, new: Any, leaves: np.ndarray, spread: np.ndarray
                           ) -> np.ndarray:
    """Re-index the children's spread ``[8 M]`` (order: leaf, then cell) to ``new``'s leaf order
    (``-1`` for leaves that are not new children)."""
    (_, _, _, _), lo_old, size_old, _ = _leaf_boxes(old)
    half = size_old[leaves] / 2.0
    centres = (lo_old[leaves][:, None, :] + (_CELL[None] + 0.5) * half[:, None, :]).reshape(-1, 3)
    nn, ni, nj, nk, _ = new.query_cells(centres)
    flat_new = np.full(new.child.size, -1, np.int64)
    leaf_flat = np.flatnonzero(new.child.reshape(-1) == 0)
    flat_new[leaf_flat] = np.arange(leaf_flat.size)
    pos = flat_new[((nn * 2 + ni) * 2 + nj) * 2 + nk]
    out = np.full(new.n_leaves, -1.0, np.float32)
    out[pos] = spread
    return out


def merge_leaves(tree: Any, tol: float) -> tuple[Any, int]:
    """Merge every node (not the root) whose 8 cells are leaves that agree within ``tol``
    (pixel units: ``max_i |α_i - ᾱ| + max_i |c_i - c̄|``, α over the children's side; all-empty
    siblings always agree) into one leaf of their mean. One level per call; returns
    ``(new tree, nodes merged)``."""
    n = tree.n_nodes
    if n <= 1:
        return tree, 0
    flat = tree.child.reshape(n, 8)
    all_leaf = (flat == 0).all(axis=1)
    all_leaf[0] = False
    cand = np.flatnonzero(all_leaf)
    if cand.size == 0:
        return tree, 0
    depth, _ = tree._node_geometry()
    h = (0.5 ** (depth[cand] + 1))[:, None] / tree.invradius[None, :]
    h = h.mean(axis=1)
    vals = tree.data.reshape(n, 8, -1)[cand].astype(np.float32)
    mean = vals.mean(axis=1)
    a = 1.0 - np.exp(-np.maximum(vals[..., -1], 0) * h[:, None])
    am = 1.0 - np.exp(-np.maximum(mean[:, -1], 0) * h)
    c = _base_colour(vals[..., :-1], tree.data_format, tree.basis_dim)
    cm = _base_colour(mean[:, :-1], tree.data_format, tree.basis_dim)
    err = np.abs(a - am[:, None]).max(axis=1) + (a[..., None] * np.abs(c - cm[:, None])).max(
        axis=(1, 2))
    empty = (vals[..., -1] <= 0).all(axis=1)
    ok = cand[(err < tol) | empty]
    if ok.size == 0:
        return tree, 0
    # parent cell of each merged node
    cells = np.flatnonzero(tree.child.reshape(-1) > 0)
    target = cells // 8 + tree.child.reshape(-1)[cells].astype(np.int64)
    parent_cell = np.full(n, -1, np.int64)
    parent_cell[target] = cells
    pc = parent_cell[ok]
    child = tree.child.copy().reshape(-1)
    data = tree.data.copy().reshape(n * 8, -1)
    child[pc] = 0
    mean_ok = tree.data.reshape(n, 8, -1)[ok].astype(np.float32).mean(axis=1)
    data[pc] = mean_ok.astype(data.dtype)
    out = dataclasses.replace(tree, child=child.reshape(n, 2, 2, 2),
                              data=data.reshape(tree.data.shape))
    out = compact_tree(out)
    return dataclasses.replace(out, depth_limit=int(tree.depth_limit)), int(ok.size)


@dataclass(frozen=True)
class RefineOptions:
    """How :func:`refine_tree` refines.

    Attributes:
        passes: subdivision rounds; each round scores the leaves the previous one created
            (the first scores every leaf with σ > 0).
        threshold: subdivide leaves whose spread is at least this (pixel units).
        max_fraction: at most this share of the scored leaves per pass (the worst first).
        max_depth: deepest cell depth allowed (None: the tree's depth + ``passes``, at most
            ``MAX_DEPTH``).
        samples: field samples per scored / new leaf.
        merge_tol: merge siblings that agree within this (0 = no merging).
        seed: random seed of the samples. chunk: points per field call.
        show_progress: progress bars (None: on a terminal).
        averaging: value of a new leaf from its samples: "mean" or "opacity" (use the one the
            tree was extracted with).
    """

    passes: int = 1
    threshold: float = 0.02
    max_fraction: float = 0.5
    max_depth: int | None = None
    samples: int = 8
    merge_tol: float = 0.0
    seed: int = 0
    chunk: int = 1 << 17
    show_progress: bool | None = False
    averaging: str = "mean"


def refine_tree(tree: Any, field_: Any, opts: RefineOptions = RefineOptions()
                ) -> tuple[Any, list]:
    """Subdivide where one value per leaf cannot represent ``field_`` and (``merge_tol > 0``)
    merge where eight siblings agree; see the module docstring. Each pass is logged (INFO).

    Args:
        tree: the tree (not modified). field_: a radiance field of the tree's data format.
        opts: passes, threshold, sampling, merging (:class:`RefineOptions`).

    Returns:
        ``(new tree, per-pass records)`` with leaves, nodes, subdivided / merged counts.
    """
    passes, threshold, max_fraction, samples, merge_tol = (
        opts.passes, opts.threshold, opts.max_fraction, opts.samples, opts.merge_tol)
    max_depth, seed, chunk = opts.max_depth, opts.seed, opts.chunk
    if tree.data_format == "RGBA" or getattr(field_, "basis", "sh") == "plain":
        raise ConfigError("refine needs a NeRF-SH / NeRF-SG field and a tree of its format")
    for name, v, lo in (("passes", passes, 0), ("samples", samples, 1)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
            raise ConfigError(f"refine: {name} must be an integer >= {lo}, got {v!r}")
    if not 0.0 < max_fraction <= 1.0:
        raise ConfigError(f"refine: max_fraction must be in (0, 1], got {max_fraction}")
    if not threshold >= 0 or not merge_tol >= 0:
        raise ConfigError("refine: threshold and merge_tol must be >= 0")
    limit = min(MAX_DEPTH, int(tree.max_depth) + passes if max_depth is None else int(max_depth))
    records = []
    cand = None          # leaf indices to score this pass (None: every leaf with σ > 0)
    scores = None
    for p in range(passes):
        t0 = time.perf_counter()
        depth = tree.leaf_depths()
        sig = _leaf_sigma(tree)
        if cand is None:
            cand = np.flatnonzero(sig > 0)
            scores = leaf_spread(tree, field_, samples, seed + p, chunk, cand, opts.show_progress)
        keep = depth[cand] < limit
        cand, scores = cand[keep], scores[keep]
        bad = scores >= threshold
        k = int(min(bad.sum(), np.ceil(max_fraction * cand.size)))
        if k == 0:
            records.append({"pass": p + 1, "scored": int(cand.size), "subdivided": 0,
                            "leaves": int(tree.n_leaves), "nodes": int(tree.n_nodes),
                            "seconds": round(time.perf_counter() - t0, 2)})
            break
        worst = cand[np.argsort(-scores, kind="stable")[:k]]
        tree, child_spread = subdivide_leaves(tree, worst, field_, samples, seed + 100 + p,
                                              chunk, opts.show_progress, opts.averaging)
        rec = {"pass": p + 1, "scored": int(cand.size), "subdivided": k,
               "leaves": int(tree.n_leaves), "nodes": int(tree.n_nodes),
               "max_depth": int(tree.max_depth),
               "seconds": round(time.perf_counter() - t0, 2)}
        records.append(rec)
        logger.info("refine pass %d: subdivided %d of %d scored leaves -> %d leaves, depth %d "
                    "(%s s)", p + 1, k, rec["scored"], rec["leaves"], rec["max_depth"],
                    rec["seconds"])
        new_sig = _leaf_sigma(tree)
        cand = np.flatnonzero((child_spread >= 0) & (new_sig > 0))
        scores = child_spread[cand]
    if merge_tol > 0:
        total = 0
        while True:
            tree, n_m = merge_leaves(tree, merge_tol)
            total += n_m
            if n_m == 0:
                break
        records.append({"merge_tol": merge_tol, "merged": total, "leaves": int(tree.n_leaves),
                        "nodes": int(tree.n_nodes)})
        logger.info("refine merge: %d nodes merged -> %d leaves", total, tree.n_leaves)
    return tree, records


# ---------------------------------------------------------------------- the command
@dataclass
class RefineConfig:
    """Options of ``plenoctree refine`` (field docstrings are the ``--help``)."""

    tree: str = ""
    """Input tree (.npz) extracted from the run."""
    run_dir: str = ""
    """Run directory (or checkpoint) of the NeRF-SH the tree was extracted from."""
    out: str = ""
    """Output tree (.npz); default: <tree stem>_refined.npz."""
    passes: int = 1
    """Subdivision rounds (each can go one level deeper where the field still varies); `run`'s
    default -1: 1 for a 360° capture, 0 for a forward-facing one."""
    threshold: float = 0.1
    """Subdivide leaves whose sample spread is at least this (pixel units, 0-1; lego 256³:
    0.1 refines 36% of the leaves, +2.0 dB at 2.9x the leaves)."""
    max_fraction: float = 0.5
    """At most this share of the scored leaves is subdivided per pass (the worst first)."""
    max_depth: int = 0
    """Deepest cell depth (0: the tree's depth + passes, at most the package limit)."""
    samples: int = 8
    """Field samples per scored and per new leaf."""
    merge_tol: float = 0.0
    """Merge eight sibling leaves that agree within this (pixel units; 0 = no merging)."""
    averaging: str = "opacity"
    """Value of a new leaf from its samples: opacity (σ keeping the samples' mean opacity,
    opacity-weighted colour; extraction's default) or mean (of σ and coefficients); use the
    extraction's."""
    precision: str = "auto"
    """Saved precision: fp16, fp32 or auto (that of the input file)."""
    data: str = ""
    """Dataset for --eval-views (default: the one the run was trained on)."""
    eval_views: int = 0
    """Score this many evenly spaced test views before and after (0 = none)."""
    chunk: int = 1 << 17
    """Points per network call."""
    device: str = "cpu"
    """Device of the network: cpu or cuda."""
    seed: int = 0
    """Random seed of the samples."""
    show_progress: bool | None = None
    """Progress bars (None: when stderr is a terminal)."""

    def options(self) -> RefineOptions:
        """The :func:`refine_tree` options of this command."""
        return RefineOptions(passes=int(self.passes), threshold=float(self.threshold),
                             max_fraction=float(self.max_fraction),
                             max_depth=int(self.max_depth) or None, samples=int(self.samples),
                             merge_tol=float(self.merge_tol), seed=int(self.seed),
                             chunk=int(self.chunk), show_progress=self.show_progress,
                             averaging=self.averaging)

    def validated(self) -> "RefineConfig":
        """Check the option values; raises :class:`ConfigError` naming the option."""
        for name, lo in (("passes", 0), ("samples", 1), ("max_depth", 0), ("eval_views", 0),
                         ("chunk", 1)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                raise ConfigError(f"refine: --{name.replace('_', '-')} must be an integer >= "
                                  f"{lo}, got {v!r}")
        if self.max_depth > MAX_DEPTH:
            raise ConfigError(f"refine: --max-depth {self.max_depth} is past the depth limit "
                              f"{MAX_DEPTH}")
        if not 0.0 < float(self.max_fraction) <= 1.0:
            raise ConfigError(f"refine: --max-fraction must be in (0, 1], got {self.max_fraction}")
        for name in ("threshold", "merge_tol"):
            v = float(getattr(self, name))
            if not (np.isfinite(v) and v >= 0):
                raise ConfigError(f"refine: --{name.replace('_', '-')} must be >= 0, got {v}")
        if self.averaging not in AVERAGING:
            raise ConfigError(f"refine: --averaging must be one of {', '.join(AVERAGING)}, got "
                              f"{self.averaging!r}")
        if self.precision not in ("auto", "fp16", "fp32"):
            raise ConfigError(f"refine: --precision must be auto, fp16 or fp32, got "
                              f"{self.precision!r}")
        return check_bounds(self, "refine: ")


@dataclass
class RefineResult:
    """What :func:`refine` did."""

    out: Path
    leaves_before: int
    leaves_after: int
    nodes_after: int
    max_depth: int
    file_bytes: int
    seconds: float
    passes: list = field(default_factory=list)
    psnr_before: float | None = None
    psnr_after: float | None = None
    eval_views: int = 0

    def to_json(self) -> dict:
        d = dataclasses.asdict(self)
        d["out"] = str(self.out)
        return d


def _eval_psnr(tree: Any, root: str, downscale: int, background: Any, n: int) -> float:
    from ..datasets import load_dataset
    from ..evaluation import evaluate_tree
    from ..render import RenderOptions

    test = load_dataset(root, split="test", downscale=downscale, background=background,
                        limit=n, spread=True)
    ev = evaluate_tree(tree, test, None, RenderOptions(background=tuple(test.background)),
                       show_progress=False)
    return float(ev.mean_psnr)


def refine(cfg: RefineConfig) -> RefineResult:
    """Refine ``cfg.tree`` against the NeRF-SH of ``cfg.run_dir`` and save ``cfg.out``
    (atomically, with ``<out stem>.refine.json`` holding the figures). Logs the test PSNR
    before and after (with ``eval_views``) and each pass (INFO)."""
    from ..octree import load_tree, save_tree
    from .extraction import ExtractConfig, _load_run, clamp_sigma_for_fp16

    t0 = time.perf_counter()
    cfg = cfg.validated()
    if not cfg.tree:
        raise ConfigError("refine: give the tree to refine")
    tree = load_tree(cfg.tree, keep_dtype=True)
    precision = cfg.precision if cfg.precision != "auto" else (
        "fp16" if tree.data.dtype == np.float16 else "fp32")
    if tree.data.dtype != np.float32:
        tree = tree.astype(np.float32)                 # the stored copy is freed here
    field_, train_cfg, _ = _load_run(ExtractConfig(run_dir=cfg.run_dir, device=cfg.device))
    if field_.data_format != tree.data_format:
        raise ConfigError(f"{cfg.tree}: the tree is {tree.data_format} but the run's model gives "
                          f"{field_.data_format}: not the run this tree was extracted from")
    root = cfg.data or (train_cfg.data if train_cfg is not None else "")
    down = int(getattr(train_cfg, "downscale", 1) or 1)
    bg = getattr(train_cfg, "background", None)               # None: the dataset's default
    if cfg.eval_views and not Path(root).is_dir():
        raise ConfigError(f"{root}: dataset folder not found; pass --data")
    before = _eval_psnr(tree, root, down, bg, cfg.eval_views) if cfg.eval_views else None
    if before is not None:
        logger.info("refine: test PSNR before %.3f dB (%d views)", before, cfg.eval_views)
    n0 = tree.n_leaves
    new, recs = refine_tree(tree, field_, cfg.options())
    new.check_integrity("refined tree")
    after = _eval_psnr(new, root, down, bg, cfg.eval_views) if cfg.eval_views else None
    if after is not None:
        logger.info("refine: test PSNR after  %.3f dB", after)
    src = Path(cfg.tree)
    out = Path(cfg.out) if cfg.out else src.with_name(src.stem + "_refined.npz")
    if precision == "fp16":
        clamp_sigma_for_fp16(new)
    save_tree(new, out, precision=precision)
    res = RefineResult(out, int(n0), int(new.n_leaves), int(new.n_nodes), int(new.max_depth),
                       int(os.path.getsize(out)), time.perf_counter() - t0, recs, before, after,
                       int(cfg.eval_views))
    atomic_save_json(out.with_name(out.stem + ".refine.json"), res.to_json())
    return res
