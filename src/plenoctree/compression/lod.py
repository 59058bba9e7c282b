"""Level of detail: smaller trees for the web (lower SH degree, merged leaves, pruning).

Three reductions, each returning a new tree (the input is never modified):

- :func:`truncate_sh`: keep the SH bands up to ``degree`` (the L2-best lower-degree
  approximation, as the real SH basis is orthonormal).
- :func:`prune`: leaves whose own opacity ``1 - exp(-σ ℓ)`` (ℓ = mean side, world units) is
  below ``alpha_thresh`` become empty; nodes whose 8 cells are all empty leaves collapse.
- :func:`merge_to_depth`: subtrees below ``max_depth`` are merged bottom-up, 2x2x2 cells at a
  time, into one leaf that keeps the mean transmittance of axis-aligned rays:
  ``σ = mean_a( -log(mean over the 4 columns along axis a of exp(-(σ_0 + σ_1) ℓ_a)) / (2 ℓ_a) )``;
  colour coefficients are the opacity-weighted mean of the children's.

:func:`fit_to_size` applies them in order of increasing visual loss until the written file
(``.plnz`` compressed or ``.npz`` float16) fits a size budget.
"""

from __future__ import annotations

import logging
import math
import os
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

from .._bounds import check_bounds
from ..errors import ConfigError
from ..octree import Octree
from .codec import CompressOptions, compress
from .fileio import save_compressed

__all__ = ["LodOptions", "truncate_sh", "prune", "merge_to_depth", "make_lod", "fit_to_size",
           "write_tree_file"]

logger = logging.getLogger(__name__)

_MIN_T = 1e-30


@dataclass
class LodOptions:
    """One level-of-detail setting (the ``plenoctree lod`` flags: the field docstrings are
    their help)."""

    sh_degree: int | None = None
    """keep SH degrees 0..N (SH trees only; default: all)"""
    max_depth: int | None = None
    """merge cells deeper than this (root cells have depth 0; default: the tree's depth)"""
    prune_alpha: float = 0.0
    """empty leaves whose opacity 1-exp(-sigma*size) is below this (0 keeps every leaf)"""

    def validated(self) -> LodOptions:
        if self.sh_degree is not None and (isinstance(self.sh_degree, bool)
                                           or not 0 <= int(self.sh_degree) <= 4):
            raise ConfigError(f"LodOptions.sh_degree must be 0..4 or None, got {self.sh_degree!r}")
        if self.max_depth is not None and (isinstance(self.max_depth, bool)
                                           or int(self.max_depth) < 0):
            raise ConfigError(f"LodOptions.max_depth must be >= 0 or None, got {self.max_depth!r}")
        a = float(self.prune_alpha)
        if not (math.isfinite(a) and 0.0 <= a < 1.0):
            raise ConfigError(f"LodOptions.prune_alpha must be in [0, 1), got {self.prune_alpha!r}")
        return check_bounds(self, "LodOptions.")

    def describe(self) -> str:
        parts = []
        if self.sh_degree is not None:
            parts.append(f"SH degree {self.sh_degree}")
        if self.max_depth is not None:
            parts.append(f"depth <= {self.max_depth}")
        if self.prune_alpha > 0:
            parts.append(f"prune alpha < {self.prune_alpha:g}")
        return ", ".join(parts) or "unchanged"


def truncate_sh(tree: Octree, degree: int) -> Octree:
    """Keep SH bands ``0..degree``: ``SH<B>`` -> ``SH<(degree+1)^2>`` (no-op if already lower)."""
    kind_sh = tree.data_format.startswith("SH")
    if not kind_sh:
        raise ConfigError(f"truncate_sh: the tree's data format is {tree.data_format}, "
                          "not SH; only SH trees have degrees to drop")
    b_old = tree.basis_dim
    b_new = (int(degree) + 1) ** 2
    if b_new >= b_old:
        return tree.copy()
    coef = tree.data[..., :-1].reshape(tree.data.shape[:-1] + (3, b_old))[..., :b_new]
    data = np.concatenate([coef.reshape(tree.data.shape[:-1] + (3 * b_new,)),
                           tree.data[..., -1:]], axis=-1)
    return Octree(child=tree.child.copy(), data=np.ascontiguousarray(data),
                  offset=tree.offset.copy(), invradius=tree.invradius.copy(),
                  data_format=f"SH{b_new}", extra_data=None, depth_limit=tree.depth_limit,
                  ndc=tree.ndc)


def _parents(child: np.ndarray) -> np.ndarray:
    """Flat parent cell index ``node*8 + c`` of every node (-1 for the root), int64 ``[n]``."""
    n = child.shape[0]
    flat = child.reshape(-1).astype(np.int64)
    cells = np.flatnonzero(flat)
    parent = np.full(n, -1, dtype=np.int64)
    parent[cells // 8 + flat[cells]] = cells
    return parent


def _compact(child: np.ndarray, data: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop nodes with ``keep == False`` (their parent cells must already be leaves)."""
    n = child.shape[0]
    new_index = np.cumsum(keep) - 1
    flat = child.reshape(n, 8).astype(np.int64)[keep]
    old = np.flatnonzero(keep)
    p, c = np.nonzero(flat)
    out = np.zeros_like(flat)
    out[p, c] = new_index[old[p] + flat[p, c]] - p
    return out.astype(np.int32).reshape(-1, 2, 2, 2), np.ascontiguousarray(data[keep])


def _merge_cells(vals: np.ndarray, cell_world: np.ndarray, is_rgba: bool) -> np.ndarray:
    """Merge ``[M, 2, 2, 2, D]`` leaf cells of side ``cell_world [3]`` into ``[M, D]``."""
    sigma = np.maximum(vals[..., -1].astype(np.float64), 0.0)          # [M, 2, 2, 2]
    sig_axes = []
    for a in range(3):
        tau = sigma.sum(axis=1 + a) * cell_world[a]                     # [M, 2, 2] columns
        t_mean = np.exp(-tau).mean(axis=(1, 2))
        sig_axes.append(-np.log(np.maximum(t_mean, _MIN_T)) / (2.0 * cell_world[a]))
    sig = np.minimum(np.mean(sig_axes, axis=0), sigma.reshape(len(vals), -1).max(axis=1))
    alpha = 1.0 - np.exp(-sigma * float(np.mean(cell_world)))          # [M, 2, 2, 2]
    w = alpha.reshape(len(vals), 8)
    wsum = w.sum(axis=1, keepdims=True)
    coef = vals[..., :-1].reshape(len(vals), 8, -1).astype(np.float64)
    mean = (coef * w[..., None]).sum(axis=1) / np.maximum(wsum, 1e-12)
    mean[wsum[:, 0] <= 0] = 0.0
    return np.concatenate([mean, sig[:, None]], axis=1).astype(vals.dtype)


def _collapse(tree: Octree, select: Callable[[np.ndarray, np.ndarray, int], np.ndarray]) -> Octree:
    """Bottom-up: a node whose 8 cells are leaves and that ``select(cells_child, vals, depth)``
    marks is merged into its parent cell. Returns a new, compacted tree."""
    child = tree.child.copy()
    data = tree.data.astype(np.float32, copy=True)
    n = child.shape[0]
    if n == 1:
        return tree.copy()
    depth = tree.node_depths()
    parent = _parents(child)
    keep = np.ones(n, dtype=bool)
    is_rgba = tree.data_format == "RGBA"
    radius_world = 0.5 / tree.invradius                                  # [3]
    for t in range(int(depth.max()), 0, -1):
        nodes = np.flatnonzero(depth == t)
        leafy = (child[nodes].reshape(len(nodes), 8) == 0).all(axis=1)
        nodes = nodes[leafy]
        if nodes.size == 0:
            continue
        vals = data[nodes]
        chosen = select(child[nodes], vals, t)
        nodes, vals = nodes[chosen], vals[chosen]
        if nodes.size == 0:
            continue
        cell_world = 2.0 * radius_world * 0.5 ** (t + 1)                 # side of these cells
        merged = _merge_cells(vals, cell_world, is_rgba)
        pc = parent[nodes]
        data.reshape(-1, data.shape[-1])[pc] = merged
        child.reshape(-1)[pc] = 0
        keep[nodes] = False
    new_child, new_data = _compact(child, data, keep)
    out = Octree(child=new_child, data=new_data, offset=tree.offset.copy(),
                 invradius=tree.invradius.copy(), data_format=tree.data_format,
                 extra_data=None if tree.extra_data is None else tree.extra_data.copy(),
                 depth_limit=-1, ndc=tree.ndc)
    out.depth_limit = max(out.max_depth, 0)
    return out


def merge_to_depth(tree: Octree, max_depth: int) -> Octree:
    """Merge every cell deeper than ``max_depth`` into its ancestor at that depth."""
    if int(max_depth) < 0:
        raise ConfigError(f"merge_to_depth: max_depth must be >= 0, got {max_depth}")
    return _collapse(tree, lambda c, v, t: np.full(len(v), t > int(max_depth)))


def prune(tree: Octree, alpha_thresh: float) -> Octree:
    """Empty leaves with opacity ``1 - exp(-σ ℓ) < alpha_thresh``; collapse all-empty nodes."""
    out = tree.copy()
    out.data = out.data.astype(np.float32)
    leaf = out.child == 0
    sizes = out.leaf_sizes().mean(axis=1)
    sig = np.maximum(out.data[leaf][:, -1].astype(np.float64), 0.0)
    weak = (1.0 - np.exp(-sig * sizes)) < float(alpha_thresh)
    rows = out.data[leaf]
    rows[weak] = 0.0
    out.data[leaf] = rows
    return _collapse(out, lambda c, v, t: (v[..., -1].reshape(len(v), 8) <= 0).all(axis=1))


def make_lod(tree: Octree, options: LodOptions) -> Octree:
    """Apply :class:`LodOptions` (SH truncation, then depth merge, then pruning)."""
    opts = options.validated()
    out = tree
    if opts.sh_degree is not None and tree.data_format.startswith("SH"):
        out = truncate_sh(out, opts.sh_degree)
    if opts.max_depth is not None and out.max_depth > opts.max_depth:
        out = merge_to_depth(out, opts.max_depth)
    if opts.prune_alpha > 0:
        out = prune(out, opts.prune_alpha)
    if out is tree:
        out = tree.copy()
    out.check_integrity("lod: tree")
    return out


def write_tree_file(tree: Octree, path: str | os.PathLike,
                    compress_options: CompressOptions | None = None) -> int:
    """Write ``tree`` as ``.plnz`` (compressed, by suffix) or native ``.npz`` (float16 if it
    fits, else float32). Returns the file size in bytes."""
    path = Path(path)
    if path.suffix == ".plnz":
        return save_compressed(compress(tree, compress_options), path)
    from ..octree.io import save_tree

    fits16 = float(np.abs(tree.data).max(initial=0.0)) <= float(np.finfo(np.float16).max)
    save_tree(tree, path, precision="fp16" if fits16 else "fp32")
    return path.stat().st_size


def _schedule(tree: Octree, base: LodOptions) -> list[LodOptions]:
    """Candidate settings, in order of increasing loss, all at least as strong as ``base``."""
    deg0 = tree.sh_degree if base.sh_degree is None else min(base.sh_degree, tree.sh_degree or 0)
    depth0 = tree.max_depth if base.max_depth is None else min(base.max_depth, tree.max_depth)
    out = [base]

    def add(**kw: object) -> None:
        cand = replace(out[-1], **kw)
        if cand != out[-1]:
            out.append(cand)

    add(prune_alpha=max(base.prune_alpha, 0.01))
    if deg0 is not None and deg0 > 2:
        add(sh_degree=2)                                   # the paper's web setting (SH9)
    add(prune_alpha=max(base.prune_alpha, 0.05))
    for d in range(depth0 - 1, max(depth0 - 4, 2) - 1, -1):
        add(max_depth=d)
        if deg0 is not None and d == depth0 - 1 and deg0 > 1:
            add(sh_degree=1)
    if deg0 is not None and deg0 > 0:
        add(sh_degree=0)
    return out


def fit_to_size(tree: Octree, out_path: str | os.PathLike, target_mb: float,
                base: LodOptions | None = None, compress_options: CompressOptions | None = None
                ) -> tuple[LodOptions, int]:
    """Write the least-reduced level of detail of ``tree`` whose file is ``<= target_mb``.

    Tries :func:`make_lod` with the settings of a fixed schedule (prune 1 %, SH degree 2,
    prune 5 %, shallower depths, SH degree 1, degree 0), each on top of ``base``, writing each
    candidate to a temporary file next to ``out_path``; the first that fits is moved onto
    ``out_path``.

    Returns:
        ``(options used, file size in bytes)``.
    Raises:
        ConfigError: ``target_mb`` is not positive or no candidate fits (the message gives the
        smallest size reached).
    """
    if not (math.isfinite(float(target_mb)) and float(target_mb) > 0):
        raise ConfigError(f"target size must be a positive number of MB, got {target_mb!r}")
    budget = float(target_mb) * 1e6
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    smallest = None
    base = (base or LodOptions()).validated()
    for cand in _schedule(tree, base):
        lod = make_lod(tree, cand)
        with tempfile.TemporaryDirectory(dir=out_path.parent) as tmp:
            tmp_path = Path(tmp) / out_path.name
            size = write_tree_file(lod, tmp_path, compress_options)
            logger.info(f"  {cand.describe():<45s} {lod.n_leaves:>10d} leaves  {size / 1e6:9.2f} MB")
            if size <= budget:
                os.replace(tmp_path, out_path)
                return cand, size
        smallest = size if smallest is None else min(smallest, size)
    raise ConfigError(f"no level of detail fits {target_mb} MB (smallest tried: "
                      f"{smallest / 1e6:.2f} MB); allow a larger size")
